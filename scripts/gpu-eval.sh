#!/usr/bin/env bash
# Evaluation on a machine with a real GPU, sized for one device call (10 minutes a
# command; at most 8 files of 16 MiB come back, no deeper than two folders):
#
#   scripts/gpu-eval.sh OUTDIR            the default evaluation, under 9 minutes
#   scripts/gpu-eval.sh --large OUTDIR    the 3M-node ladder, the 1M-node Newton step and
#                                         CuPy at 1M nodes (a second call)
#
# 0. `stickslip info` must show a discrete GPU on Vulkan with SHADER_F64, else exit 3
#    (seconds, nothing else run).
# 1. The GPU correctness tests that compare split and unsplit results bit for bit
#    (tests/gpu_split.rs, tests/gpu_launch.rs), when a test binary is given in
#    GPU_EVAL_TEST_BINS (cargo test --no-run builds them; carry them with the binary).
# 2. The benchmarks, each under a step limit its sizes can meet. Every benchmark appends
#    a record per finished solve (bench --hard: per finished case) to records.jsonl, so a
#    step stopped at its limit keeps what it finished (the hard step's records travel in
#    eval.tar.gz). A limit of 0 skips the step.
#
# OUTDIR then holds at most 8 files, none in a folder: summary.md (each step's exit status
# and seconds, the tables), info.txt, tests.log, ladder.jsonl, newton.jsonl, hard.md,
# cupy.jsonl and eval.tar.gz (every step's full output and log, frames left out).
# Exit: 0 all steps passed, 1 a step failed or ran out of time, 2 usage, 3 no usable GPU.
#
# Environment (defaults in brackets; the --large defaults after the slash):
#   STICKSLIP_BIN          the binary [target/release/stickslip]
#   GPU_EVAL_TEST_BINS     test binaries for step 1, space separated [none: step skipped]
#   GPU_EVAL_SIZES         ladder node counts, 3D [100000,1000000 / 3000000]
#   GPU_EVAL_NEWTON_SIZES  bench --newton node counts [10000,100000 / 1000000]
#   GPU_EVAL_TWIST_SIZE    run twist --size, three runs (step 4) [6 / 10]
#   GPU_EVAL_HARD_SCALE    bench --hard-scale [2 / 5]
#   GPU_EVAL_CUPY_SIZES    node counts solved by CuPy and stickslip [100000 / 1000000]
#   GPU_EVAL_PYTHON        the Python with CuPy [python3]
#   GPU_EVAL_ALLOW_CPU     1: accept a CPU adapter on Vulkan (a rehearsal on lavapipe)
#   GPU_EVAL_LIMITS        seconds per step: tests,ladder,newton,twist,hard,cupy; 0 skips
#                          [60,150,90,40,60,60 / 0,240,120,30,0,180]
# The limits against what the first NVIDIA H100 run took (docs/lab/2026-11-25-h100.md;
# 16 cores): by default tests 15 s, ladder to 1M nodes 91 s, bench --newton to 100k
# 7 s, twist at size 6 4 s, bench --hard at scale 2 24 s, CuPy at 100k 25 s (166 s in
# all, limits 460 s); with --large the 3M ladder 177 s, the 1M Newton step 77 s, twist
# at size 10 12 s, CuPy at 1M ~60 s (generation and export) + ~3 x 30 s (reading the
# 1M-node system for each precision): limits 540 s.
set -uo pipefail

large=0
if [ "${1:-}" = "--large" ]; then
    large=1
    shift
fi
if [ $# -ne 1 ]; then
    echo "usage: scripts/gpu-eval.sh [--large] OUTDIR" >&2
    exit 2
fi
out=$1
here=$(cd "$(dirname "$0")" && pwd)
bin=${STICKSLIP_BIN:-target/release/stickslip}
py=${GPU_EVAL_PYTHON:-python3}
test_bins=${GPU_EVAL_TEST_BINS:-}
if [ $large = 1 ]; then
    sizes=${GPU_EVAL_SIZES:-3000000}
    newton_sizes=${GPU_EVAL_NEWTON_SIZES:-1000000}
    twist_size=${GPU_EVAL_TWIST_SIZE:-10}
    hard_scale=${GPU_EVAL_HARD_SCALE:-5}
    cupy_sizes=${GPU_EVAL_CUPY_SIZES:-1000000}
    limits=${GPU_EVAL_LIMITS:-0,240,120,30,0,180}
else
    sizes=${GPU_EVAL_SIZES:-100000,1000000}
    newton_sizes=${GPU_EVAL_NEWTON_SIZES:-10000,100000}
    twist_size=${GPU_EVAL_TWIST_SIZE:-6}
    hard_scale=${GPU_EVAL_HARD_SCALE:-2}
    cupy_sizes=${GPU_EVAL_CUPY_SIZES:-100000}
    limits=${GPU_EVAL_LIMITS:-60,150,90,40,60,60}
fi
IFS=, read -r t_tests t_ladder t_newton t_twist t_hard t_cupy <<< "$limits"
for t in "$t_tests" "$t_ladder" "$t_newton" "$t_twist" "$t_hard" "$t_cupy"; do
    case $t in
        '' | *[!0-9]*)
            echo "gpu-eval: GPU_EVAL_LIMITS='$limits': expected six whole numbers of seconds" >&2
            exit 2
            ;;
    esac
done

if [ ! -x "$bin" ]; then
    echo "gpu-eval: no stickslip binary at $bin (build with cargo build --release, or set STICKSLIP_BIN)" >&2
    exit 2
fi
mkdir -p "$out" || exit 2
# Every step's files go to a work folder; OUTDIR gets the few files listed above.
work=$(mktemp -d "${TMPDIR:-/tmp}/gpu-eval.XXXXXX") || exit 2
trap 'rm -rf "$work"' EXIT

# 0. A discrete GPU on Vulkan with SHADER_F64, or nothing else runs.
timeout --kill-after=2 20 "$bin" info > "$out/info.txt" 2>&1
rc=$?
want='(Vulkan, DiscreteGpu;.*shader_f64 true'
# A rehearsal on a CPU adapter (lavapipe) sets GPU_EVAL_ALLOW_CPU=1.
[ "${GPU_EVAL_ALLOW_CPU:-}" = 1 ] && want='(Vulkan, \(DiscreteGpu\|Cpu\);.*shader_f64 true'
if [ $rc -ne 0 ] || ! grep -q "$want" "$out/info.txt"; then
    echo "gpu-eval: no discrete GPU on Vulkan with SHADER_F64 (stickslip info exited $rc):" >&2
    head -c 2000 "$out/info.txt" >&2
    exit 3
fi

summary=$out/summary.md
failed=0
{
    echo "# stickslip GPU evaluation$([ $large = 1 ] && echo ' (--large)')"
    echo
    echo "- date: $(date -u +%Y-%m-%dT%H:%M:%SZ)"
    echo "- host: $(uname -n), $(nproc) cores, $(awk '/MemTotal/ {printf "%.0f GiB", $2/1048576}' /proc/meminfo)"
    echo "- binary: $bin ($("$bin" --version 2>/dev/null || echo unknown))"
    echo "- adapter: $(grep -m1 '^adapter 0:' "$out/info.txt" | cut -c1-200)"
    echo
    echo "| step | limit s | exit | seconds | records kept |"
    echo "|---|---|---|---|---|"
} > "$summary"

# step NAME LIMIT_S COMMAND...: runs COMMAND under `timeout` (LIMIT_S 0: skipped) and
# appends a row with the records its records.jsonl kept.
step() {
    local name=$1 limit=$2
    shift 2
    if [ "$limit" -eq 0 ]; then
        echo "| $name | 0 | skipped | | |" >> "$summary"
        return 0
    fi
    echo "gpu-eval: $name (limit ${limit} s): $*" >&2
    local t0 rc secs kept what
    t0=$(date +%s.%N)
    timeout --signal=TERM --kill-after=5 "$limit" "$@"
    rc=$?
    secs=$(awk -v a="$t0" -v b="$(date +%s.%N)" 'BEGIN {printf "%.1f", b - a}')
    kept=$(cat "$work/$name"/records.jsonl 2>/dev/null | wc -l)
    what=$rc
    { [ $rc -eq 124 ] || [ $rc -eq 137 ]; } && what="$rc (over ${limit} s)"
    echo "| $name | $limit | $what | $secs | $kept |" >> "$summary"
    if [ $rc -ne 0 ]; then
        failed=1
        echo "gpu-eval: $name exited $what" >&2
    fi
    return 0
}
mkdir -p "$work/tests" "$work/ladder" "$work/newton" "$work/twist" "$work/hard" "$work/cupy"

# 1. Split against unsplit, bit for bit.
if [ -n "$test_bins" ]; then
    tests_all() {
        local b rc=0
        for b in $test_bins; do
            STICKSLIP_REQUIRE_GPU=1 "$b" --test-threads 1 || rc=1
        done
        return $rc
    }
    # A carried test binary runs the carried stickslip, not the path cargo built it with.
    STICKSLIP_BIN=$(cd "$(dirname "$bin")" && pwd)/$(basename "$bin")
    export test_bins STICKSLIP_BIN
    export -f tests_all
    step tests "$t_tests" bash -c tests_all > "$work/tests/tests.log" 2>&1
else
    echo "| tests | | not given (GPU_EVAL_TEST_BINS) | | |" >> "$summary"
fi

# 2. The solver ladder, 3D.
step ladder "$t_ladder" "$bin" bench --quick --sizes "$sizes" --dims 3 \
    --oracle-max-nodes 100000 --out "$work/ladder" > "$work/ladder/tables.md" 2> "$work/ladder/log.txt"

# 3. The Newton step.
step newton "$t_newton" "$bin" bench --newton --sizes "$newton_sizes" --reps 1 \
    --out "$work/newton" > "$work/newton/tables.md" 2> "$work/newton/log.txt"

# 4. One step of a twist, the whole Newton step on the GPU against the CPU loop, and the
#    device loop with the multilevel preconditioner against its default (Jacobi with the
#    aggregates): linear seconds and iterations of each in the summary.
twist_both() {
    "$bin" run twist --size "$twist_size" --steps 1 --newton gpu --quiet --overwrite \
        --out "$work/twist/gpu" || return 1
    "$bin" run twist --size "$twist_size" --steps 1 --newton gpu --preconditioner multilevel \
        --quiet --overwrite --out "$work/twist/gpu-multilevel" || return 1
    "$bin" run twist --size "$twist_size" --steps 1 --solver cg --quiet --overwrite \
        --out "$work/twist/cpu" || return 1
}
export work bin twist_size
export -f twist_both
step twist "$t_twist" bash -c twist_both 2> "$work/twist/log.txt"
# summary.json's figures, one line per run (grep: the device machine may lack jq); the
# table joins the others at the end of the summary.
twist_field() {
    grep -o "\"$2\": *[^,}]*" "$1/summary.json" 2>/dev/null | head -1 | sed 's/.*: *//; s/"//g'
}
{
    echo "twist --size $twist_size --steps 1:"
    echo
    echo "| run | nodes | preconditioner | Newton | CG iterations | linear s | wall s |"
    echo "|---|---|---|---|---|---|---|"
    for r in gpu gpu-multilevel cpu; do
        d=$work/twist/$r
        [ -s "$d/summary.json" ] || continue
        printf '| %s | %s | %s | %s | %s | %.3f | %.3f |\n' "$r" "$(twist_field "$d" nodes)" \
            "$(twist_field "$d" preconditioner)" "$(twist_field "$d" newton_iterations)" \
            "$(twist_field "$d" linear_iterations)" "$(twist_field "$d" linear_seconds)" \
            "$(twist_field "$d" wall_seconds)"
    done
} > "$work/twist/runs.md"

# 5. The hard cases: f64 against mixed.
step hard "$t_hard" "$bin" bench --hard --hard-scale "$hard_scale" \
    --out "$work/hard" 2> "$work/hard/log.txt"

# 6. CuPy's CG beside stickslip's GPU CG (f64, Jacobi, 1e-8) on the same systems.
if [ "$t_cupy" -gt 0 ] && "$py" -c "import cupy, cupyx.scipy.sparse.linalg" 2>/dev/null; then
    cupy_all() {
        local n dir p tol
        for n in ${cupy_sizes//,/ }; do
            dir=$work/cupy/n$n
            "$bin" generate --quiet --dim 3 --nodes "$n" --out-dir "$dir/sys" || return 1
            "$bin" export --quiet --hessian "$dir/sys/H.mtx" --gradient "$dir/sys/g.mtx" \
                --constraints "$dir/sys/bc.json" --no-mtx --out-dir "$dir/export" || return 1
            "$py" "$here/cupy_cg.py" "$dir/export" --tol 1e-8 > "$work/cupy/cupy-n$n.json" || return 1
            printf '{"tool":"cupy","nodes":%s,"report":%s}\n' "$n" \
                "$(tr -d '\n' < "$work/cupy/cupy-n$n.json")" >> "$work/cupy/records.jsonl"
            for p in f64 mixed f32; do
                tol=1e-8
                [ $p = f32 ] && tol=1e-6
                "$bin" solve --quiet --hessian "$dir/sys/H.mtx" --gradient "$dir/sys/g.mtx" \
                    --constraints "$dir/sys/bc.json" --solver gpu --precision $p \
                    --preconditioner jacobi --coarse none --tol $tol --out "$dir/dx-$p.mtx" \
                    --report "$work/cupy/stickslip-$p-n$n.json" || return 1
                printf '{"tool":"stickslip-%s","nodes":%s,"report":%s}\n' "$p" "$n" \
                    "$(tr -d '\n' < "$work/cupy/stickslip-$p-n$n.json")" >> "$work/cupy/records.jsonl"
            done
            # The systems are large; keep the results, not the inputs.
            rm -rf "$dir"
        done
    }
    export work bin py here cupy_sizes
    export -f cupy_all
    step cupy "$t_cupy" bash -c cupy_all 2> "$work/cupy/log.txt"
elif [ "$t_cupy" -eq 0 ]; then
    echo "| cupy | 0 | skipped | | |" >> "$summary"
else
    echo "| cupy | $t_cupy | CuPy not importable by $py | | |" >> "$summary"
fi

# The few files that come back: the records, the tables and one tarball without frames.
cp "$work/tests/tests.log" "$out/tests.log" 2>/dev/null
for s in ladder newton cupy; do
    [ -s "$work/$s/records.jsonl" ] && cp "$work/$s/records.jsonl" "$out/$s.jsonl"
done
[ -s "$work/hard/hard.md" ] && cp "$work/hard/hard.md" "$out/hard.md"
{
    for f in "$work"/ladder/*.md "$work"/newton/*.md "$work"/twist/runs.md; do
        [ -s "$f" ] || continue
        echo
        echo "## ${f#"$work"/}"
        echo
        head -c 200000 "$f"
    done
} >> "$summary"
# Inputs are left out: frames, matrices, checkpoints and the CuPy step's systems (a step
# stopped at its limit leaves them behind).
tar -C "$work" --exclude=frames --exclude='*.mtx' --exclude='*.petsc' --exclude='checkpoint*.bin' \
    --exclude='cupy/n[0-9]*' -czf "$out/eval.tar.gz" . 2>/dev/null
# Still over 16 MiB (a runaway log): only the files under 1 MiB, so the tarball stays whole.
if [ "$(stat -c %s "$out/eval.tar.gz")" -gt $((16 << 20)) ]; then
    (cd "$work" && find . -type f -size -1M ! -path '*/frames/*' ! -path './cupy/n*' -print0 |
        tar --null -T - -czf "$out/eval.tar.gz")
fi
# A text file over 16 MiB is cut (a tarball never is: it would not open).
for f in "$out"/*; do
    case $f in *.tar.gz) continue ;; esac
    [ -f "$f" ] && [ "$(stat -c %s "$f")" -gt $((16 << 20)) ] && truncate -s 16M "$f"
done
cat "$summary"
exit $failed
