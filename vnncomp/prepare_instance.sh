#!/usr/bin/env bash
# VNN-COMP harness: nothing to prepare (mrcert reads gzipped or plain files as they are);
# checks that the files exist so that a wrong path fails here, not in the timed run.
# usage: prepare_instance.sh v1 CATEGORY ONNX VNNLIB
set -euo pipefail
[ "${1:-}" = v1 ] || { echo "prepare_instance.sh: expected the version string v1, got '${1:-}'" >&2; exit 1; }
for f in "$3" "$4"; do
  [ -f "$f" ] || [ -f "$f.gz" ] || { echo "prepare_instance.sh: no file $f" >&2; exit 1; }
done
exit 0
