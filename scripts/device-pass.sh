#!/usr/bin/env bash
# One batched pass on the GPU machine (the `device` tool's `run`), so a session lent a GPU
# spends its 30 minutes measuring, not setting up. It writes to $OUT (the folder the device
# tool brings back; default ./device-out):
#   info.txt        glossrt info (variant, device)
#   bench.json      glossrt bench at $SIZE (default 1920x1080) for $BENCHES (default: all)
#   bench-bspvt-512.json  the bspvt bench at 512x512 (issue 6's per-vertex target size),
#                   when $BENCHES is unset or names bspvt
#   pytest.txt      the test suite on this device when pytest is importable (else skipped)
# Run it after installing the wheels printed by ../shared/tools/device-wheels, e.g.
#   python3 -m pip install -q --no-index --no-deps --no-compile --no-cache-dir --upgrade \
#     --target /tmp/site .whl/*.whl && export PYTHONPATH=/tmp/site:$PWD/src && \
#     bash scripts/device-pass.sh
# Variables: DEVICE (gpu), SIZE (1920x1080), BENCHES (space-separated names, default all),
# REPEATS (9), TESTS (pytest arguments, default "tests -q -x"), PYTHON (python3).
# On a CPU, `DEVICE=cpu SIZE=64x36 REPEATS=1 BENCHES=specaa TESTS=skip bash
# scripts/device-pass.sh` checks the script itself.
set -uo pipefail
OUT=${OUT:-device-out}
DEVICE=${DEVICE:-gpu}
SIZE=${SIZE:-1920x1080}
REPEATS=${REPEATS:-9}
PYTHON=${PYTHON:-python3}
TESTS=${TESTS:-tests -q -x}
mkdir -p "$OUT"
run() { "$PYTHON" -c 'import sys; from glossrt.cli import main; sys.exit(main())' "$@"; }

run --device "$DEVICE" info > "$OUT/info.txt" 2>&1
status=$?
cat "$OUT/info.txt"
if [ $status -ne 0 ]; then
    echo "device-pass: glossrt info failed on device '$DEVICE' (see $OUT/info.txt)" >&2
    exit $status
fi

only=()
if [ -n "${BENCHES:-}" ]; then
    # shellcheck disable=SC2206
    only=(--only $BENCHES)
fi
run --device "$DEVICE" bench --size "$SIZE" --repeats "$REPEATS" --json "$OUT/bench.json" \
    "${only[@]}" > "$OUT/bench.txt" 2>&1
echo "device-pass: bench exit $? ($OUT/bench.json)"
case " ${BENCHES:-bspvt} " in
    *" bspvt "*)
        # issue 6's target is per-vertex shading of a 512x512 view (bspvt-vertex-frozen)
        run --device "$DEVICE" bench --only bspvt --size 512x512 --repeats "$REPEATS" \
            --json "$OUT/bench-bspvt-512.json" > "$OUT/bench-bspvt-512.txt" 2>&1
        echo "device-pass: bspvt 512x512 exit $? ($OUT/bench-bspvt-512.json)"
        ;;
esac

if [ "$TESTS" != "skip" ] && "$PYTHON" -c 'import pytest' 2>/dev/null; then
    # shellcheck disable=SC2086
    GLOSSRT_DEVICE=$DEVICE "$PYTHON" -m pytest $TESTS > "$OUT/pytest.txt" 2>&1
    echo "device-pass: pytest exit $? ($OUT/pytest.txt)"
    tail -3 "$OUT/pytest.txt"
else
    echo "device-pass: tests skipped (TESTS=skip or pytest not importable)"
fi
