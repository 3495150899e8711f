"""The thin client: stream, store, render and measure frames."""

# Its kernels cache where the visibility package keys numba's cache (``kernel_cache``).
import visibility  # noqa: F401
