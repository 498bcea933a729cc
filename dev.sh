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
    test) .venv/bin/lint-imports && exec .venv/bin/python -m pytest -q "$@" ;;
    setup) exit 0 ;;
    *)    echo "usage: ./dev.sh run|test|setup [args]" >&2; exit 2 ;;
esac
