#!/usr/bin/env bash
# The GPU checks of jaxsh, as one script: run it from any directory on a machine with a CUDA device and a
# CUDA build of jaxlib (`pip install -e ".[cuda,tests]"`, or an image that already has JAX for CUDA).
#
#   bash benchmarks/gpu_checks.sh [OUTDIR]      (default: gpu_out; $OUT if set)
#
# jaxsh is used from the checkout (PYTHONPATH), not installed. Packages that the machine lacks can be
# given as wheels in .whl/ (installed with --no-deps into a temporary folder first). For a machine without
# network whose image has JAX for CUDA, equinox, optimistix, lineax, jaxtyping, scipy, pytest, hypothesis
# (session 23's H200), these were enough, fetched elsewhere for its Python (3.12 there):
#   pip download --no-deps --only-binary=:all: --python-version 3.12 --implementation cp \
#     --platform manylinux_2_28_x86_64 --platform manylinux_2_27_x86_64 --platform manylinux_2_17_x86_64 \
#     -d .whl jaxopt trimesh embreex OpenImageIO beartype jsonschema jsonschema-specifications referencing rpds-py
# Steps, each with its own time limit (seconds; JAXSH_GPU_BUDGET bounds the whole run, default 420;
# JAXSH_GPU_STEPS, a list of the step names below, runs only those):
#   1. machine: GPU, driver, JAX and the packages' versions;
#   2. gpu_tests: the tests that need a GPU (tests/test_scale.py: the sharded fit on the GPU equals the CPU's; the
#      host BLAS limit stays off the GPU path);
#   3. bench_scale: benchmarks/bench_scale.py --gpu (a batch of 64 captures and one 24-view capture on 1 GPU);
#   4. bench_gpu: benchmarks/bench_gpu.py (GPU against the host's CPU backend, same process: speed and agreement);
#   5. demo: `jaxsh demo` on the GPU (the end-to-end pipeline, its held-out errors);
#   6. suite: the test suite (not slow, no notebooks) on the GPU backend, in the background from the start, on
#      other cores than steps 2-5 (taskset), until the budget ends (then interrupted, so pytest still prints
#      the failures so far): every test's outcome is in suite.log.
# Outputs in OUTDIR: checks.log, suite.log, bench_scale.json, bench_gpu.json, demo.json.
set -u
cd "$(dirname "$0")/.."
out=${1:-${OUT:-gpu_out}}
mkdir -p "$out"
py=${PYTHON:-python3}
budget=${JAXSH_GPU_BUDGET:-420}
t0=$(date +%s)
log="$out/checks.log"
: >"$log"
say() { echo "$*" | tee -a "$log"; }

if [ -d .whl ] && ls .whl/*.whl >/dev/null 2>&1; then
    $py -m pip install -q --no-index --no-deps --no-compile --no-cache-dir --upgrade --target /tmp/jaxsh_site .whl/*.whl \
        || { say "installing .whl/ failed"; exit 1; }
    export PYTHONPATH=/tmp/jaxsh_site${PYTHONPATH:+:$PYTHONPATH}
fi
export PYTHONPATH="$PWD${PYTHONPATH:+:$PYTHONPATH}" PYTHONUNBUFFERED=1 XLA_PYTHON_CLIENT_PREALLOCATE=false
command -v taskset >/dev/null || taskset() { shift 2; "$@"; }  # without util-linux: no pinning
ncpu=$(nproc)
half=$((ncpu / 2))
fg_cpus="0-$((half - 1))"
bg_cpus="$half-$((ncpu - 1))"

# 6. the suite, in the background, on the other half of the cores
suite_pid=
suite_args=(-m "not slow" -p no:cacheprovider -p no:benchmark -v --tb=short -rfE -n "$half" --dist loadfile)
$py -c "import pytest_timeout" 2>/dev/null && suite_args+=(--timeout 240)
[[ " ${JAXSH_GPU_STEPS:-suite} " == *" suite "* ]] && (cd "$PWD" && taskset -c "$bg_cpus" timeout -s INT -k 10 $((budget - 25)) $py -m pytest "${suite_args[@]}" tests \
    >"$out/suite.log" 2>&1; echo "suite exit $?" >>"$out/suite.log") &
[[ " ${JAXSH_GPU_STEPS:-suite} " == *" suite "* ]] && suite_pid=$!

steps=" ${JAXSH_GPU_STEPS:-machine gpu_tests bench_scale bench_gpu demo suite} "
step() {  # step NAME LIMIT CMD...: run on the first half of the cores, log, report exit code and time
    local name=$1 limit=$2 s rc
    shift 2
    [[ "$steps" == *" $name "* ]] || return 0
    local left=$((budget - 20 - $(date +%s) + t0))
    [ "$limit" -gt "$left" ] && limit=$left
    if [ "$limit" -le 5 ]; then say "== $name: skipped (budget spent)"; return; fi
    say "== $name (limit ${limit} s)"
    s=$(date +%s)
    taskset -c "$fg_cpus" timeout "$limit" "$@" >>"$log" 2>&1
    rc=$?
    say "== $name: exit $rc in $(($(date +%s) - s)) s"
}

step machine 60 bash -c "nvidia-smi -L; nvidia-smi --query-gpu=name,driver_version,memory.total --format=csv,noheader;
  $py -c 'from importlib.metadata import version as v
names = \"jax jaxlib numpy scipy equinox optimistix lineax jaxtyping jaxopt trimesh embreex OpenImageIO pytest hypothesis\"
print(*[n + \" \" + v(n) for n in names.split()], sep=\", \")
import jax, jaxsh, solvers
print(\"devices\", jax.devices(), \"default backend\", jax.default_backend(), \"- jaxsh\", jaxsh.__version__, \"imports\")'"
step gpu_tests 120 $py -m pytest -p no:cacheprovider -p no:benchmark -v -rs tests/test_scale.py -k "gpu or blas"
step bench_scale 110 $py benchmarks/bench_scale.py --gpu --devices 1 --json "$out/bench_scale.json"
step bench_gpu 150 $py benchmarks/bench_gpu.py --json "$out/bench_gpu.json"
step demo 90 $py -m solvers.cli demo --out /tmp/jaxsh_demo_gpu --json "$out/demo.json"

[ -z "$suite_pid" ] && { say "== done in $(($(date +%s) - t0)) s (no suite)"; exit 0; }
wait "$suite_pid"
count() { grep -cE "^\[gw[0-9]+\] \[ *[0-9]+%\] $1 " "$out/suite.log"; }
say "== suite: $(count PASSED) passed, $(count FAILED) failed, $(count ERROR) errors, $(count SKIPPED) skipped;" \
    "$(grep -E '^(=+ )?[0-9]+ (passed|failed)|suite exit' "$out/suite.log" | tail -2 | tr '\n' ' ')"
say "== failures:"
grep -E '^(FAILED|ERROR) |\] (FAILED|ERROR) ' "$out/suite.log" | sort -u | cut -c1-300 | tee -a "$log" | head -60
say "== done in $(($(date +%s) - t0)) s"
