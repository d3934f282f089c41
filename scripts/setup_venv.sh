#!/usr/bin/env bash
# Create (or update) the project's Python 3.11 virtual environment in .venv.
# Every install is constrained to numpy<2: Blender 4.2-5.0 embed numpy 1.26.
set -euo pipefail
cd "$(dirname "$0")/.."
PY=${PYTHON:-python3.11}
if [ ! -x .venv/bin/python ]; then
  "$PY" -m venv .venv
fi
stamp=.venv/.requirements.sha
want=$(cat requirements/dev.txt requirements/constraints.txt | sha256sum | cut -d' ' -f1)
if [ "$(cat "$stamp" 2>/dev/null)" != "$want" ]; then
  .venv/bin/python -m pip install -q --upgrade pip
  .venv/bin/python -m pip install -q -r requirements/dev.txt -c requirements/constraints.txt
  echo "$want" > "$stamp"
fi
