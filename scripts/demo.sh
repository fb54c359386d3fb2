#!/usr/bin/env bash
# The main job, on a fresh machine: set up, serve the bundled demo model on loopback, and have the
# example robot client render a view and estimate pose + configuration from it.
#   scripts/demo.sh [--port N] [--model NAME]
set -euo pipefail
cd "$(dirname "$0")/.."
port=8765
model=clamp
while [ $# -gt 0 ]; do
  case "$1" in
    --port) port="$2"; shift 2 ;;
    --model) model="$2"; shift 2 ;;
    *) echo "scripts/demo.sh: error: unknown option $1 (use --port N, --model NAME)" >&2; exit 2 ;;
  esac
done
scripts/install.sh dev
.venv/bin/narf serve --models models --host 127.0.0.1 --port "$port" &
server=$!
trap 'kill $server 2>/dev/null; wait $server 2>/dev/null || true' EXIT
for _ in $(seq 1 120); do
  if .venv/bin/python -c "import httpx,sys; sys.exit(httpx.get('http://127.0.0.1:$port/readyz').status_code != 200)" 2>/dev/null; then
    break
  fi
  kill -0 $server 2>/dev/null || { echo "scripts/demo.sh: error: the server exited; see its output above" >&2; exit 1; }
  sleep 0.5
done
.venv/bin/python examples/robot_client.py --url "http://127.0.0.1:$port" --model "$model"
