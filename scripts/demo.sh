#!/usr/bin/env bash
# One command: install what is missing, then serve the bundled demo scene in the browser workbench.
set -euo pipefail
source "$(dirname "${BASH_SOURCE[0]}")/setup.sh"
exec .venv/bin/workbench serve --demo "$@"
