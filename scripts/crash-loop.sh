#!/usr/bin/env bash
# Runs test files again and again, one pytest process per run, to catch an intermittent
# crash: core dumps on, Python's faulthandler on (pytest's default), and for each crashed run
# a gdb backtrace of every thread from its core file. Counts runs, failures and crashes.
# Usage: scripts/crash-loop.sh PYTHON RUNS TEST_FILE... (output: crash-loop/<n>.log, cores)
set -uo pipefail
py=${1:?usage: crash-loop.sh PYTHON RUNS TEST_FILE...}
runs=${2:?usage: crash-loop.sh PYTHON RUNS TEST_FILE...}
shift 2
[ $# -gt 0 ] || { echo "crash-loop.sh: name at least one test file" >&2; exit 2; }
out=${CRASH_LOOP_OUT:-crash-loop}
mkdir -p "$out"
ulimit -c unlimited
crashes=0
failures=0
for ((i = 1; i <= runs; i++)); do
    log="$out/$i.log"
    # each run in a folder of its own, so that its core file (kernel.core_pattern "core")
    # is found there
    dir=$(mktemp -d)
    abs=()
    for f in "$@"; do abs+=("$(realpath "$f")"); done
    (cd "$dir" && "$py" -X faulthandler -m pytest -q -p no:cacheprovider \
        --rootdir "$OLDPWD" -c "$OLDPWD/pyproject.toml" "${abs[@]}") > "$log" 2>&1
    rc=$?
    if [ $rc -ge 128 ] || grep -q "Fatal Python error" "$log"; then
        crashes=$((crashes + 1))
        core=$(ls "$dir"/core* 2>/dev/null | head -1)
        if [ -n "$core" ] && command -v gdb > /dev/null; then
            gdb -batch -ex "thread apply all bt" "$py" "$core" > "$out/$i.gdb.txt" 2>&1
            mv "$core" "$out/$i.core"
        fi
        echo "run $i: CRASHED (status $rc): $log"
    elif [ $rc -ne 0 ]; then
        failures=$((failures + 1))
        echo "run $i: failed (status $rc): $log"
    else
        echo "run $i: passed"
    fi
    rm -rf "$dir"
done
echo "crash-loop: $runs runs of $*: $crashes crashed, $failures failed"
[ $crashes -eq 0 ] && [ $failures -eq 0 ]
