"""The ``sampling`` core: from-point sampling, the same method as the sampled ground truth."""

from visibility.cores.sampling.core import MAX_SAMPLES, SamplingCore, SamplingParams

__all__ = ["MAX_SAMPLES", "SamplingCore", "SamplingParams"]
