# Environment shared by the scripts: headless OpenGL through Mesa's OSMesa, a project-local numba
# cache (compiled kernels survive between runs), unbuffered output.
export PYOPENGL_PLATFORM=${PYOPENGL_PLATFORM:-osmesa}
export NUMBA_CACHE_DIR=${NUMBA_CACHE_DIR:-$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)/.numba_cache}
export PYTHONUNBUFFERED=1
# Bytecode written on first import: with PYTHONDONTWRITEBYTECODE set (some machines' default)
# and a venv installed without .pyc files (uv compiles none), every process (each server, worker
# and CLI a test starts) compiled numpy, scipy, numba and ours from source again, seconds each.
unset PYTHONDONTWRITEBYTECODE
export MPLBACKEND=Agg
export OMP_WAIT_POLICY=${OMP_WAIT_POLICY:-passive}  # spinning OpenMP threads starve a shared 2-core machine
