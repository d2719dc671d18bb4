#!/usr/bin/env bash
# Every benchmark on a GPU, most important first, inside one time budget.
#
#   bash benchmarks/gpu.sh [BUDGET_S]    # default 3600 s; writes benchmarks/results/*_gpu.{json,md}
#
# Each script runs with `--platform gpu` (its JAX rows on the GPU; cvxpy and NumPy rows on the
# host's CPU) under `timeout`, limited to its own cap and to what is left of the budget; a
# script is skipped when less than 30 s are left. Logs: $LOG_DIR (default a temporary folder),
# one per script, and a summary line per script on stdout. PLATFORM=cpu and QUICK=1 (every
# script's --quick, results under $OUT_DIR) smoke-test this runner on a machine without a GPU.
# ONLY="NAME ..." runs only the named scripts (in this file's order), e.g. to spend a short
# device lease on the figures not yet recorded.
set -u
cd "$(dirname "$0")/.."
budget=${1:-3600}
platform=${PLATFORM:-gpu}
out_dir=${OUT_DIR:-benchmarks/results}
log_dir=${LOG_DIR:-$(mktemp -d)}
mkdir -p "$log_dir" "$out_dir"
deadline=$(( $(date +%s) + budget ))
quick=()
if [[ "${QUICK:-0}" == 1 ]]; then quick=(--quick); fi

bench() {  # bench NAME CAP_S ARGS...: python benchmarks/NAME.py --platform ... ARGS
    local name=$1 cap=$2; shift 2
    if [[ -n "${ONLY:-}" && " $ONLY " != *" $name "* ]]; then return; fi
    local left=$(( deadline - $(date +%s) ))
    if (( left < 30 )); then
        echo "$name: skipped (budget spent)"
        return
    fi
    local limit=$(( cap < left ? cap : left )) t0=$SECONDS rc=0
    PYTHONUNBUFFERED=1 timeout "$limit" python3 "benchmarks/$name.py" --platform "$platform" --out "$out_dir" \
        "${quick[@]}" "$@" >"$log_dir/$name.log" 2>&1 || rc=$?
    echo "$name: exit $rc after $(( SECONDS - t0 )) s (limit $limit s$( (( rc == 124 )) && echo ', timed out'))"
}

# The figures issue "Fast by default" asks of a GPU: KF steps/s at B = 1e4, 1e5, 1e6 (+ the
# Wasserstein DRKF rows), PF particle-steps/s at N = 1e4 x 1e3 runs, Wasserstein DRKF steps/s.
bench kf_throughput 300
bench particle_filter 180 --sis
bench wasserstein_solver 180 --no-cvxpy --no-profile
# The rest: the same scripts as on the CPU, smaller where cvxpy (CPU) dominates.
# steady_state_solver: n = 2 and 4 (n = 10 did not finish inside a 180 s slot on an H200);
# parallel_kf: n = 2 (the sequential smoother costs ~0.2 ms per step on a GPU; n = 8 needs a
# longer slot than this budget's share).
bench steady_state_solver 180 --no-grad --instances 3 --sizes 2x1 4x2
bench parallel_kf 120 --T 100 1000 10000 --dims 2 --repeats 3
bench call_floor 60
bench marginal_solver 120 --instances 5
bench square_root 120 --systems 1
