#!/usr/bin/env bash
# The test command behind `make test`.
#
# Default: the suite on two pytest-xdist worker processes (fewer on a 1-core machine), each
# test file on one worker (`--dist loadfile`: a file's module fixtures are built once); a test
# whose worker crashes, or hangs past pytest-timeout's limit (pyproject.toml), is run once
# more on a fresh worker, loudly (tests/crash_rerun.py, which also repairs pytest-xdist 3.8.0's
# loadfile scheduler: after a crash it could leave the run hanging with every worker idle).
# A crash fails the run even when the rerun passes, unless the crashed test is listed in
# tests/crash_rerun.py's KNOWN_UPSTREAM as a crash shown to be an upstream bug (with a minimal
# reproduction in docs/ARCHITECTURE.md, "Crashed tests"); the end of the run prints how many
# tests crashed and were rerun.
# A cold run is bound by Dr.Jit's single-threaded kernel compilation, so two workers nearly
# halve it: on the 2-core VM with an empty HOME, `bash .ci/run` took
# 5m41-6m10 in all with 2 workers (two runs) against 8m08 in one process (2026-11-23).
#
# GLOSSRT_TEST_WORKERS=1 (or pytest-xdist missing): one pytest process. If it is killed by a
# signal (exit status >= 128, e.g. 139 for SIGSEGV), the test file it was in and every file
# after it are run once more, loudly, and the run fails unless the crashed test (the last one
# started and not finished, from the progress file tests/conftest.py writes) is a known
# upstream crash. A failed test (before or after a crash), a second crash or a hung test
# (pytest-timeout ends the process with status 1) fails the run. GLOSSRT_TEST_WORKERS is
# capped at 4.
# Usage: scripts/run-tests.sh PYTHON [pytest args...]
set -uo pipefail
py=${1:?usage: run-tests.sh PYTHON [pytest args]}
shift
cores=$(nproc 2>/dev/null || echo 1)
workers=${GLOSSRT_TEST_WORKERS:-$(( cores < 2 ? 1 : 2 ))}
[ "$workers" -gt 4 ] && workers=4
if [ "$workers" -gt 1 ] && "$py" -c "import xdist" 2>/dev/null; then
    exec "$py" -m pytest -q -n "$workers" --dist loadfile --max-worker-restart 3 "$@"
elif [ "$workers" -gt 1 ]; then
    echo "!! $workers test workers wanted, but pytest-xdist is not installed: one process" >&2
fi
progress=$(mktemp)
trap 'rm -f "$progress"' EXIT
GLOSSRT_TEST_PROGRESS=$progress "$py" -m pytest -q "$@"
rc=$?
if [ $rc -lt 128 ]; then
    exit $rc
fi
echo "!! pytest was killed by signal $((rc - 128))" >&2
last=$(grep '^done ' "$progress" | tail -n 1 | cut -d' ' -f2 | cut -d: -f1)
mapfile -t files < <(ls tests/test_*.py | sort)
rest=()
started=${last:+0}
for f in "${files[@]}"; do
    if [ -z "$last" ] || [ "$f" = "$last" ] || [ "${started:-0}" = 1 ]; then
        rest+=("$f")
        started=1
    fi
done
crashed=$(awk '$1 == "start" {s = substr($0, 7)} $1 == "done" && substr($0, 6) == s {s = ""}
             END {print s}' "$progress")
earlier_failed=$(grep -c '^FAILED ' "$progress")
echo "!! running again from ${rest[0]} (${#rest[@]} files); failures before the crash: $earlier_failed" >&2
"$py" -m pytest -q "$@" "${rest[@]}"
rc=$?
if [ "$earlier_failed" -gt 0 ]; then
    grep '^FAILED ' "$progress" >&2
    exit 1
fi
if ! PYTHONPATH="$(dirname "$0")/../tests" "$py" -c 'import sys; from crash_rerun import known_upstream
sys.exit(0 if known_upstream(sys.argv[1]) else 1)' "${crashed:-?}" 2>/dev/null; then
    echo "!! 1 test crashed and was rerun: ${crashed:-unknown}: NOT a known upstream crash:" \
         "the run fails (tests/crash_rerun.py, KNOWN_UPSTREAM)" >&2
    exit 1
fi
echo "!! 1 test crashed and was rerun: $crashed: a known upstream crash" >&2
exit $rc
