#!/usr/bin/env bash
# One command: install what is missing, lint, then run the whole test suite (browser tests included).
set -euo pipefail
source "$(dirname "${BASH_SOURCE[0]}")/setup.sh"
# The linter first (pyproject.toml's [tool.ruff]): a lint error fails the run before the tests start.
.venv/bin/ruff check --quiet .
exec .venv/bin/python -m pytest -q "$@"
