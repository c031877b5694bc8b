#!/usr/bin/env bash
# VNN-COMP harness: install mrcert (system packages, .venv) from this checkout.
# usage: install_tool.sh v1
set -euo pipefail
[ "${1:-}" = v1 ] || { echo "install_tool.sh: expected the version string v1, got '${1:-}'" >&2; exit 1; }
cd "$(dirname "$(realpath "$0")")/.."
make install
