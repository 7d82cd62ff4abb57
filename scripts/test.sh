#!/usr/bin/env bash
# One command: install what is missing, then run the whole test suite (browser tests included).
set -euo pipefail
source "$(dirname "${BASH_SOURCE[0]}")/setup.sh"
exec .venv/bin/python -m pytest -q "$@"
