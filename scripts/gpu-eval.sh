#!/usr/bin/env bash
# One-command evaluation on a machine with a real GPU and the Vulkan loader:
#
#   scripts/gpu-eval.sh OUTDIR
#
# Runs, each step under its own time limit so the whole stays within about 10 minutes:
#   1. `stickslip info`                                   -> OUTDIR/info.txt
#   2. the solver ladder in 3D (f32, f64, mixed against CPU CG and a 1e-12 reference),
#      `bench --quick` at GPU_EVAL_SIZES                  -> OUTDIR/ladder/
#   3. `bench --newton` at GPU_EVAL_NEWTON_SIZES, when the binary has it
#                                                         -> OUTDIR/newton/
#   4. `run twist --steps 1` at GPU_EVAL_TWIST_SIZE with the GPU Newton loop and with the
#      CPU loop (CPU CG, every core): wall and linear-solve seconds, bytes moved
#                                                         -> OUTDIR/twist/
#   5. the hard-case speed table, `bench --hard`          -> OUTDIR/hard/
#   6. where CuPy imports: the same generated systems solved by CuPy's Jacobi CG
#      (scripts/cupy_cg.py) beside `stickslip solve --solver gpu` -> OUTDIR/cupy/
# and OUTDIR/summary.md with each step's exit status and seconds. A step that fails or
# runs out of time is recorded there and the script goes on; it exits 1 when any did.
#
# Environment (defaults in brackets):
#   STICKSLIP_BIN          the binary [target/release/stickslip]
#   GPU_EVAL_SIZES         ladder node counts [100000,1000000,3000000]
#   GPU_EVAL_NEWTON_SIZES  bench --newton node counts [10000,100000,1000000]
#   GPU_EVAL_TWIST_SIZE    run twist --size [10]
#   GPU_EVAL_HARD_SCALE    bench --hard-scale [5]
#   GPU_EVAL_CUPY_SIZES    node counts solved by CuPy and stickslip [100000,1000000]
#   GPU_EVAL_PYTHON        the Python with CuPy [python3]
#   GPU_EVAL_LIMITS        seconds per step: ladder,newton,twist,hard,cupy
#                          [180,120,60,60,90]: with `info` (30) at most 540 s in all
set -uo pipefail

if [ $# -ne 1 ]; then
    echo "usage: scripts/gpu-eval.sh OUTDIR" >&2
    exit 2
fi
out=$1
here=$(cd "$(dirname "$0")" && pwd)
bin=${STICKSLIP_BIN:-target/release/stickslip}
sizes=${GPU_EVAL_SIZES:-100000,1000000,3000000}
newton_sizes=${GPU_EVAL_NEWTON_SIZES:-10000,100000,1000000}
twist_size=${GPU_EVAL_TWIST_SIZE:-10}
hard_scale=${GPU_EVAL_HARD_SCALE:-5}
cupy_sizes=${GPU_EVAL_CUPY_SIZES:-100000,1000000}
py=${GPU_EVAL_PYTHON:-python3}
IFS=, read -r t_ladder t_newton t_twist t_hard t_cupy <<< "${GPU_EVAL_LIMITS:-180,120,60,60,90}"

if [ ! -x "$bin" ]; then
    echo "gpu-eval: no stickslip binary at $bin (build with cargo build --release, or set STICKSLIP_BIN)" >&2
    exit 2
fi
mkdir -p "$out" || exit 2
summary=$out/summary.md
failed=0
{
    echo "# stickslip GPU evaluation"
    echo
    echo "- date: $(date -u +%Y-%m-%dT%H:%M:%SZ)"
    echo "- host: $(uname -n), $(nproc) cores, $(awk '/MemTotal/ {printf "%.0f GiB", $2/1048576}' /proc/meminfo)"
    echo "- binary: $bin ($("$bin" --version 2>/dev/null || echo unknown))"
    echo
    echo "| step | exit | seconds | output |"
    echo "|---|---|---|---|"
} > "$summary"

# step NAME LIMIT_S OUTPUT COMMAND...: runs COMMAND under `timeout`, appends a row.
step() {
    local name=$1 limit=$2 dest=$3
    shift 3
    echo "gpu-eval: $name (limit ${limit} s): $*" >&2
    local t0 rc
    t0=$(date +%s.%N)
    timeout --signal=TERM --kill-after=10 "$limit" "$@"
    rc=$?
    local secs
    secs=$(awk -v a="$t0" -v b="$(date +%s.%N)" 'BEGIN {printf "%.1f", b - a}')
    local what=$rc
    [ $rc -eq 124 ] && what="124 (over ${limit} s)"
    echo "| $name | $what | $secs | $dest |" >> "$summary"
    if [ $rc -ne 0 ]; then
        failed=1
        echo "gpu-eval: $name exited $what" >&2
    fi
    return $rc
}

# 1. The adapter, its features and limits.
step info 30 info.txt sh -c "\"$bin\" info > \"$out/info.txt\" 2>&1"

# 2. The solver ladder, 3D.
step ladder "$t_ladder" ladder/ "$bin" bench --quick --sizes "$sizes" --dims 3 \
    --oracle-max-nodes 100000 --out "$out/ladder" 2> "$out/ladder.log"

# 3. The Newton step, where this build has it.
if "$bin" bench --help 2>/dev/null | grep -q -- '--newton'; then
    # One timed repetition after the warm-up: at 1M nodes the CPU side alone takes tens
    # of seconds a phase.
    step newton "$t_newton" newton/ "$bin" bench --newton --sizes "$newton_sizes" --reps 1 \
        --out "$out/newton" 2> "$out/newton.log"
else
    echo "| newton | not in this build | | |" >> "$summary"
fi

# 4. One step of a large twist, the whole Newton step on the GPU against the CPU loop.
if "$bin" run --help 2>/dev/null | grep -q -- '--newton'; then
    twist_both() {
        "$bin" run twist --size "$twist_size" --steps 1 --newton gpu --quiet --overwrite \
            --out "$out/twist/gpu" || return 1
        "$bin" run twist --size "$twist_size" --steps 1 --solver cg --quiet --overwrite \
            --out "$out/twist/cpu" || return 1
    }
    mkdir -p "$out/twist"
    export out bin twist_size
    export -f twist_both
    step twist "$t_twist" twist/ bash -c twist_both 2> "$out/twist.log"
else
    echo "| twist | not in this build | | |" >> "$summary"
fi

# 5. The hard cases: f64 against mixed at a larger scale.
step hard "$t_hard" hard/ "$bin" bench --hard --hard-scale "$hard_scale" \
    --out "$out/hard" 2> "$out/hard.log"

# 6. CuPy's CG on the same systems, beside stickslip's GPU CG (f64, Jacobi, 1e-8).
if "$py" -c "import cupy, cupyx.scipy.sparse.linalg" 2>/dev/null; then
    cupy_all() {
        local n dir
        for n in ${cupy_sizes//,/ }; do
            dir=$out/cupy/n$n
            "$bin" generate --quiet --dim 3 --nodes "$n" --out-dir "$dir/sys" || return 1
            "$bin" export --quiet --hessian "$dir/sys/H.mtx" --gradient "$dir/sys/g.mtx" \
                --constraints "$dir/sys/bc.json" --no-mtx --out-dir "$dir/export" || return 1
            "$py" "$here/cupy_cg.py" "$dir/export" --tol 1e-8 > "$out/cupy/cupy-n$n.json" || return 1
            for p in f64 mixed f32; do
                local tol=1e-8
                [ $p = f32 ] && tol=1e-6
                "$bin" solve --quiet --hessian "$dir/sys/H.mtx" --gradient "$dir/sys/g.mtx" \
                    --constraints "$dir/sys/bc.json" --solver gpu --precision $p \
                    --preconditioner jacobi --coarse none --tol $tol --out "$dir/dx-$p.mtx" \
                    --report "$out/cupy/stickslip-$p-n$n.json" || return 1
            done
            # The systems are large; keep the results, not the inputs.
            rm -rf "$dir"
        done
    }
    mkdir -p "$out/cupy"
    export out bin py here cupy_sizes
    export -f cupy_all
    step cupy "$t_cupy" cupy/ bash -c cupy_all
else
    echo "| cupy | CuPy not importable by $py | | |" >> "$summary"
fi

cat "$summary"
exit $failed
