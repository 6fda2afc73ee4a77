#!/usr/bin/env bash
# Installs edi-live with its test extra and runs the whole test suite.
# On Debian-like machines where we are root, it also installs Chromium (for the viewer's browser test)
# when it is missing; elsewhere that one test skips and says why.
set -euo pipefail
cd "$(dirname "$0")/.."
if ! command -v chromium >/dev/null 2>&1 && [ "$(id -u)" = 0 ] && command -v apt-get >/dev/null 2>&1; then
    (apt-get update -qq && DEBIAN_FRONTEND=noninteractive apt-get install -y -qq chromium >/dev/null) \
        || echo "tools/test.sh: could not install chromium; the MJPEG browser test will skip" >&2
fi
python -m pip install -q -e ".[test]"
exec python -m pytest -q "$@"
