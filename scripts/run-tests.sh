#!/usr/bin/env bash
# The test command behind `make test`: the suite in three pytest processes (test files split
# alphabetically). A process killed by a signal (exit status >= 128, e.g. 139 for SIGSEGV) is
# run once more, loudly: Dr.Jit 1.5 has crashed inside a dr.freeze call at random, about once
# in several full runs (seen 2026-11-23 in Renderer.trace on a cold kernel cache; the same
# tests pass on rerun), and one such crash must not hide the other groups' results. A test
# that fails, or a crash that repeats, fails the run.
# Usage: scripts/run-tests.sh PYTHON [pytest args...]
set -uo pipefail
py=${1:?usage: run-tests.sh PYTHON [pytest args]}
shift
mapfile -t files < <(ls tests/test_*.py | sort)
n=${#files[@]}
groups=3
status=0
for ((g = 0; g < groups; g++)); do
    lo=$((g * n / groups))
    hi=$(((g + 1) * n / groups))
    part=("${files[@]:lo:hi-lo}")
    [ ${#part[@]} -eq 0 ] && continue
    echo "== tests, group $((g + 1))/$groups: ${part[0]} .. ${part[-1]}"
    "$py" -m pytest -q "$@" "${part[@]}"
    rc=$?
    if [ $rc -ge 128 ]; then
        echo "!! group $((g + 1)): pytest was killed by signal $((rc - 128)); running the group once more" >&2
        "$py" -m pytest -q "$@" "${part[@]}"
        rc=$?
    fi
    if [ $rc -ne 0 ]; then
        echo "!! group $((g + 1)) failed (exit status $rc)" >&2
        status=1
    fi
done
exit $status
