#!/usr/bin/env bash
# Set up (if needed) and run the whole test suite, slow end-to-end tests included at a small size.
set -euo pipefail
cd "$(dirname "$0")/.."
scripts/install.sh dev
exec .venv/bin/python -m pytest -q "$@"
