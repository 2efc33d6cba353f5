#!/usr/bin/env bash
# The device checks of the engine in one run, for a session lent the GPU machine (one
# NVIDIA GPU, 16 CPU cores, no network; its software is listed in the device tool's notes).
#
# Here, first (network): `make device-wheels` puts in .whl/ (ignored by git) emccdcal's
# own wheel and the pure-Python packages of its core that machine lacks (array-api-compat,
# h5netcdf, emcee, tomli-w). Then, from the session: device run with command
# "bash benchmarks/device_check.sh", carry [".whl"], timeout_s 590. Everything it prints
# also lands in $OUT.
#
# What it runs, each step bounded (a guess of each step's time, never run there yet):
#   1. the GPU and JAX tests of tests/test_calibrate.py (CuPy's and JAX's GPU against NumPy);
#   2. benchmarks/bench_gpu.py on a 128 x 128 x 5 x 5000 series, both registers, CuPy,
#      then the default register through JAX's GPU;
#   3. benchmarks/bench_sensor.py: 1 against 16 local processes on a 128 x 128 x 5 x 2000
#      series (16 tiles, so one each), the efficiency docs/benchmarks.md asks for.
set -uo pipefail
OUT=${OUT:-/tmp/device-out}
mkdir -p "$OUT"
export PYTHONUNBUFFERED=1
python3 -m pip install -q --no-index --no-deps --no-compile --no-cache-dir --upgrade \
    --target /tmp/site .whl/*.whl || exit 1
export PYTHONPATH=/tmp/site
nvidia-smi -L | tee "$OUT/machine.log"
python3 -c "import jax; print('jax', jax.__version__, jax.devices())" | tee -a "$OUT/machine.log"
timeout 100 python3 -m pytest -q -p no:cacheprovider -W ignore tests/test_calibrate.py \
    -k "gpu or jax" 2>&1 | tee "$OUT/tests.log"
cd benchmarks || exit 1
timeout 200 python3 bench_gpu.py --sizes 128 --frames 5000 --keep /tmp/gpu \
    2>&1 | tee "$OUT/bench_gpu.log"
timeout 60 python3 bench_gpu.py --sizes 128 --frames 5000 --keep /tmp/gpu --device jax \
    --em-models cascade 2>&1 | tee "$OUT/bench_gpu_jax.log"
timeout 200 python3 bench_sensor.py --sizes 128 --frames 2000 --keep /tmp/sensor \
    --workers 1,16 --processes 2>&1 | tee "$OUT/processes.log"
