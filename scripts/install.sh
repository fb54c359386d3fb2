#!/usr/bin/env bash
# The one way this project is installed: README, CI and both Dockerfiles call this script.
#   scripts/install.sh [EXTRAS]      e.g. "dev" (default) or "service"
# CPU installs pin torch through constraints/cpu.txt; set NARF_CONSTRAINTS= to install a GPU torch.
set -euo pipefail
cd "$(dirname "$0")/.."
extras="${1:-dev}"
constraints="${NARF_CONSTRAINTS-constraints/cpu.txt}"
venv="${NARF_VENV-.venv}"
if [ -n "$venv" ]; then
  [ -x "$venv/bin/python" ] || python3 -m venv "$venv"
  py="$venv/bin/python"
else
  py=python3
fi
pip_args=(--disable-pip-version-check -q)
[ -n "$constraints" ] && pip_args+=(-c "$constraints")
"$py" -m pip install "${pip_args[@]}" -e ".[$extras]" -e clients/python
