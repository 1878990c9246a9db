#!/usr/bin/env bash
# The one prepared run for a lent GPU machine with many cores (issue 28, items 3 and 4), in
# one device call: the GPU placement of the focus measure and the accumulation
# (bench_gpu.py), the torch operators' tests on the GPU (pytest --device cuda), then the
# process placement measured on 2, 8 and 16 of its cores with 1, 4 and 'auto' band workers,
# in band threads (since 2026-12-04 night: the band processes' tasks in threads) and band
# processes (bench_parallel.py), then the scaling model's
# inputs measured there on 8 cores (bench_scaling.py), so that its 8-core prediction can be
# set beside the 8-core measurement, then the focus measure and depth stage alone with 1, 2,
# 4 and 8 band processes and band task threads (bench_bands.py: does their CPU a frame grow
# with K where each band has a core of its own?), and the band processes' model checked against those scans
# (bench_band_model.py). Each part runs under its own time limit and writes its
# results as it goes: a part cut short or failing leaves the others' results.
#
#   bash bench/gpu_wheels.sh           # here, once: the packages the machine lacks (.whl/)
#   # one device call, carry [".whl"], timeout_s 600:
#   bash bench/lent_machine.sh          # writes into $OUT: machine.txt, log.txt and
#                                       # results.tar (8 files at most come back), the
#                                       # tar rewritten after each part
#
# Smoke run on any machine (CPU torch, small sizes; the wheels not installed):
#   OUT=/tmp/lent SMOKE=1 bash bench/lent_machine.sh
# PARTS="cuda-tests cores" (names from: gpu cuda-tests cores model bands band-model)
# runs only those;
# PAR_ARGS and BANDS_ARGS replace the cores and bands parts' options (cases, rounds).
set -u
out=${OUT:?OUT: the folder the results are written to}
mkdir -p "$out"
res=$(mktemp -d)  # the parts' result files, packed into $out/results.tar after each part
py=${PYTHON:-python3}
log="$out/log.txt"
if [ -z "${SMOKE:-}" ]; then
  "$py" -m pip install -q --no-index --no-deps --no-compile --no-cache-dir --target /tmp/site \
    .whl/*.whl || { echo "installing .whl/ failed" >&2; exit 2; }
  export PYTHONPATH=/tmp/site
  data=../shared/datasets/pertuz-simu02  # where tests/conftest.py looks
  if [ ! -f "$data/imdata.mat" ] && [ -d .whl/pertuz-simu02 ]; then
    mkdir -p "$(dirname "$data")" && cp -r .whl/pertuz-simu02 "$data"
  fi
  gpu=(--out "$res" --frames 300 --rounds 2)
  # 13 cases (repeats left out), ~120 s a round there: the first round fits its limit (the
  # report is written after every round); band threads against band processes
  par=(--frames 400 --rounds 2 --cores 2,8,16 --workers 1,4,auto --bands threads,processes)
  sca=(--frames 300 --rounds 2 --cores 8)
  bnd=(--workers 1 2 4 8 --processes --task-threads --rounds 2)
  # seconds (gpu, cores, model, cuda-tests, bands); 2026-12-04 there: gpu 61-90 s, cores
  # 173 s (one round), model 69-84 s, the CUDA tests 17 s, bands (without task threads)
  # ~90 s
  limits=(120 200 90 60 160)
else
  gpu=(--out "$res" --device cpu --quick --frames 40)
  par=(--frames 60 --rounds 1 --cores 1,2 --workers 1,auto --bands processes)
  sca=(--frames 40 --rounds 1 --cores 2 --band-frames 8 --band-rounds 1)
  bnd=(--workers 1 2 --processes --task-threads --rounds 1)
  limits=(300 300 300 300 300)
fi
export PYTHONUNBUFFERED=1
{
  echo "== machine"; date -u; nproc; uname -r
  grep -m1 "model name" /proc/cpuinfo; free -g | head -2
  nvidia-smi -L 2>&1 | head -2
  df -hT /tmp /dev/shm 2>&1
  "$py" -c 'import sys, numpy, cv2, torch; print(sys.version.split()[0], "numpy",
numpy.__version__, "opencv", cv2.__version__, "torch", torch.__version__,
"cuda", torch.cuda.is_available())'
} > "$out/machine.txt" 2>&1
cat "$out/machine.txt"
[ -n "${PAR_ARGS:-}" ] && read -r -a par <<< "$PAR_ARGS"
[ -n "${BANDS_ARGS:-}" ] && read -r -a bnd <<< "$BANDS_ARGS"
parts=" ${PARTS:-gpu cuda-tests cores model bands band-model} "
part() {  # part NAME SECONDS COMMAND...: one bench under its limit, its output in the log
  local name=$1 limit=$2; shift 2
  [[ $parts == *" $name "* ]] || return 0
  local t0=$SECONDS
  echo "== $name (limit $limit s)" | tee -a "$log"
  timeout --kill-after=10 "$limit" "$@" >>"$log" 2>&1
  echo "== $name: exit $? after $((SECONDS - t0)) s" | tee -a "$log"
  tar -C "$res" -cf "$out/results.tar" .
}
part gpu "${limits[0]}" "$py" bench/bench_gpu.py "${gpu[@]}"
dev=cuda; [ -n "${SMOKE:-}" ] && dev=cpu
part cuda-tests "${limits[3]}" "$py" -m pytest -q -o addopts= -p no:cacheprovider \
  --device "$dev" tests/stages/test_cuda.py tests/stages/test_focus_measure.py \
  tests/stages/test_focus_operators.py
part cores "${limits[1]}" "$py" bench/bench_parallel.py "${par[@]}" --modes processes \
  --sources memory --method default --outputs /tmp/sffscan-out \
  --out "$res/parallel_cores.md"
part model "${limits[2]}" "$py" bench/bench_scaling.py "${sca[@]}" --outputs /tmp/sffscan-out \
  --out "$res/scaling_cores.md"
part bands "${limits[4]}" "$py" bench/bench_bands.py "${bnd[@]}" --out "$res/bands_cores"
if [ -f "$res/scaling_cores.json" ] && [ -f "$res/bands_cores.json" ] \
   && [ -f "$res/parallel_cores.json" ]; then  # measures nothing: the three results above
  part band-model 60 "$py" bench/bench_band_model.py --scaling "$res/scaling_cores.json" \
    --bands "$res/bands_cores.json" --scans "$res/parallel_cores.json" \
    --out "$res/band_model.md"
fi
tail -c 6000 "$log"
