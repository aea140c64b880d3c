#!/usr/bin/env bash
# Makes sure a libLLVM >= 16 is usable by Dr.Jit's CPU backend.
# Installs Debian's libllvm19 when none is found and we run as root; otherwise says what to do.
set -u
py=${1:-python3}
if "$py" -m glossrt.backend; then exit 0; fi
if [ "$(id -u)" = "0" ] && command -v apt-get >/dev/null 2>&1; then
  echo "glossrt: installing libllvm19 with apt-get (needed by Dr.Jit's CPU backend)"
  if (apt-get update -qq && DEBIAN_FRONTEND=noninteractive apt-get install -y -qq libllvm19) >/tmp/glossrt-apt.log 2>&1; then
    "$py" -m glossrt.backend && exit 0
  fi
  echo "glossrt: apt-get could not install libllvm19 (log: /tmp/glossrt-apt.log)."
fi
cat >&2 <<'TXT'
glossrt: no libLLVM >= 16 found, and it could not be installed automatically.
  Debian/Ubuntu:  sudo apt-get update && sudo apt-get install -y libllvm19
  Other systems:  install LLVM >= 16 and export DRJIT_LIBLLVM_PATH=/path/to/libLLVM.so
  (A CUDA GPU alone also works: export GLOSSRT_DEVICE=gpu)
TXT
exit 1
