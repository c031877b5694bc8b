#!/usr/bin/env bash
# VNN-COMP harness: answer one instance into RESULT (unsat, sat with its counterexample,
# unknown, timeout or error) within TIMEOUT seconds of this process's start.
# usage: run_instance.sh v1 CATEGORY ONNX VNNLIB RESULT TIMEOUT
# MRCERT_VNNCOMP_ARGS: further settings (default tracking=off: no MLflow run is recorded;
# give tracking=sqlite to record each instance in the store).
set -uo pipefail
[ "${1:-}" = v1 ] || { echo "run_instance.sh: expected the version string v1, got '${1:-}'" >&2; exit 1; }
ROOT="$(dirname "$(realpath "$0")")/.."
rm -f "$5"
# shellcheck disable=SC2086  # the settings are words
exec "${MRCERT:-$ROOT/.venv/bin/mrcert}" task=verify "task.onnx=$3" "task.vnnlib=$4" "task.result=$5" \
  "task.timeout=$6" ${MRCERT_VNNCOMP_ARGS:-tracking=off}
