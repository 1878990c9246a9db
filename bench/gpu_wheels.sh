#!/usr/bin/env bash
# The wheels a lent GPU machine needs to run bench/bench_gpu.py, gathered here into .whl/
# (ignored by git; the device tool carries it). That machine's image has Python 3.12 with
# torch (CUDA), numpy, opencv-python-headless, scipy, threadpoolctl, msgpack, packaging,
# typing-extensions, PyYAML, fsspec and tqdm, and no network: the rest of what the scan
# and the operators' tests (PyWavelets) import comes from here, with sffscan's own wheel.
# The versions are this checkout's.
#
#   bash bench/gpu_wheels.sh            # here, once (a few MB)
#   then, on the device (one call, 'carry': [".whl"]):
#   python3 -m pip install -q --no-index --no-deps --no-compile --no-cache-dir --target /tmp/site .whl/*.whl \
#     && export PYTHONPATH=/tmp/site && python3 bench/bench_gpu.py --out "$OUT"
set -euo pipefail
cd "$(dirname "$0")/.."
grep -qx '/.whl/' .git/info/exclude 2>/dev/null || echo /.whl/ >> .git/info/exclude
rm -rf .whl && mkdir -p .whl
py=${PYTHON:-python3}
version() { "$py" -c "import importlib.metadata as m, sys; print(m.version(sys.argv[1]))" "$1"; }
wanted=()
for name in pydantic pydantic-core annotated-types typing-inspection zarr numcodecs donfig \
            google-crc32c zstandard PyWavelets; do
  wanted+=("$name==$(version "$name")")
done
"$py" -m pip download -q --no-deps --only-binary=:all: --python-version 3.12 \
  --implementation cp --platform manylinux_2_28_x86_64 --platform manylinux_2_27_x86_64 \
  --platform manylinux_2_17_x86_64 --platform manylinux2014_x86_64 -d .whl "${wanted[@]}"
"$py" -m pip wheel -q --no-deps --no-build-isolation -w .whl .
# the third-party stack the operators' known-answer tests read (../shared is not carried;
# lent_machine.sh puts it back where tests/conftest.py looks), its licence with it
data=../shared/datasets/pertuz-simu02
[ -f "$data/imdata.mat" ] && cp -r "$data" .whl/pertuz-simu02
du -sh .whl
ls .whl
