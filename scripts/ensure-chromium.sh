#!/usr/bin/env bash
# Makes sure a Chromium for the live viewer's browser tests is installed (Debian's chromium,
# driven headless by Playwright's Python package; nothing downloads a browser at run time).
# Installs Debian's chromium when none is found and we run as root; otherwise says what to do.
set -u
for b in "${GLOSSRT_CHROMIUM:-}" /usr/bin/chromium /usr/bin/chromium-browser; do
  if [ -n "$b" ] && [ -x "$b" ]; then exit 0; fi
done
if [ "$(id -u)" = "0" ] && command -v apt-get >/dev/null 2>&1; then
  echo "glossrt: installing Debian's chromium with apt-get (the viewer's browser tests)"
  if (apt-get update -qq && DEBIAN_FRONTEND=noninteractive apt-get install -y -qq chromium) \
      >/tmp/glossrt-apt-chromium.log 2>&1 && [ -x /usr/bin/chromium ]; then
    exit 0
  fi
  echo "glossrt: apt-get could not install chromium (log: /tmp/glossrt-apt-chromium.log)."
fi
cat >&2 <<'TXT'
glossrt: no Chromium found for the live viewer's browser tests, and it could not be installed.
  Debian/Ubuntu:  sudo apt-get update && sudo apt-get install -y chromium
  Other systems:  install Chromium and export GLOSSRT_CHROMIUM=/path/to/chromium
TXT
exit 1
