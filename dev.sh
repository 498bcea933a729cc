#!/usr/bin/env bash
# Set up (idempotently) and run: `./dev.sh run [ARGS]` runs pancam-graph on the default
# scenario; `./dev.sh test [ARGS]` runs the whole test suite. Needs only Python 3.11+.
set -euo pipefail
cd "$(dirname "$0")"

PY=${PYTHON:-$(command -v python3.11 || command -v python3)}
if [ ! -x .venv/bin/python ]; then
    "$PY" -m venv .venv
fi
# Reinstall only when the dependency list changed.
stamp=.venv/.setup-stamp
want=$(sha256sum pyproject.toml | cut -d' ' -f1)
if [ "$(cat "$stamp" 2>/dev/null)" != "$want" ]; then
    echo "dev.sh: installing pancam-graph and its dependencies (gtsam, opencv, rerun, ...) into .venv" >&2
    .venv/bin/python -m pip install --quiet --upgrade pip
    .venv/bin/python -m pip install --quiet -e '.[dev,render]'
    echo "$want" > "$stamp"
fi

cmd=${1:-run}
shift || true
case "$cmd" in
    run)  exec .venv/bin/pancam-graph run "$@" ;;
    test)
        # the live web viewer test drives a headless Chromium: installed where apt can (root, or
        # sudo without a password); elsewhere that test skips and says why
        if ! command -v chromium >/dev/null && command -v apt-get >/dev/null; then
            sudo=""; [ "$(id -u)" = 0 ] || sudo="sudo -n"
            echo "dev.sh: installing chromium (apt) for the web viewer test" >&2
            { $sudo apt-get install -y -qq --no-install-recommends chromium \
                || { $sudo apt-get update -qq && $sudo apt-get install -y -qq --no-install-recommends chromium; }
            } >/dev/null 2>&1 || echo "dev.sh: chromium not installed; the browser test will skip" >&2
        fi
        # two test processes (pytest-xdist), a test file each at a time: most tests use one core
        .venv/bin/lint-imports && exec .venv/bin/python -m pytest -q -n 2 --dist loadfile "$@" ;;
    setup) exit 0 ;;
    *)    echo "usage: ./dev.sh run|test|setup [args]" >&2; exit 2 ;;
esac
