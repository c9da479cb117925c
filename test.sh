#!/usr/bin/env bash
# Install what is missing (as setup.sh does, without training), then run the whole test suite.
set -euo pipefail
cd "$(dirname "${BASH_SOURCE[0]}")"
VISFLY_SETUP_ONLY=1 bash setup.sh
exec "${PYTHON:-python3}" -m pytest -q -p no:cacheprovider "$@"
