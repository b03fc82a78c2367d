#!/usr/bin/env bash
# Train on a lent GPU machine (the workplace's `device` tool), resuming a run started here, and bring the
# checkpoint back. That machine has PyTorch, OpenCV and scikit-image but no registry and not this package,
# and takes at most 64 MiB of working tree, so a run goes in two steps:
#
#   here:   bash export/device_train.sh prepare runs/mobile-baseline
#           -> .device/: a 16 MiB library pack, the NanoTrack v3 teacher (used where onnxruntime is there), tqdm,
#              and the run's last.pt (the folder is git-ignored; carry it)
#   device: run(command="bash export/device_train.sh train export/configs/mobile-baseline.toml 8",
#               carry=[".device"], timeout_s=600)
#           -> trains for 8 minutes on the GPU (batch and workers scaled up), writes $OUT/last.pt, log.csv
#   here:   cp <files_at>/last.pt runs/mobile-baseline/last.pt; dadiff-train --config ... resumes from it
set -euo pipefail
cd "$(dirname "$0")/.."
mode=${1:?usage: device_train.sh prepare RUN_DIR | train CONFIG [MINUTES]}

if [ "$mode" = prepare ]; then
    run=${2:?usage: device_train.sh prepare RUN_DIR}
    rm -rf .device && mkdir -p .device/wheels .device/run
    dadiff-eval data pack --out .device/library --max-mib 16
    cp ../shared/weights/nanotrack/v3/nanotrack_backbone.onnx ../shared/weights/nanotrack/v3/nanotrack_head.onnx \
        .device/ 2>/dev/null || echo "no NanoTrack v3 teacher beside the checkout: the device run trains without it"
    python3 -m pip download -q --no-deps --only-binary :all: -d .device/wheels tqdm   # onnxruntime (27 MB) does not fit
    [ -f "$run/last.pt" ] && cp "$run/last.pt" .device/run/
    du -sh .device
    exit 0
fi

[ "$mode" = train ] || { echo "device_train.sh: error: unknown mode '$mode'" >&2; exit 2; }
config=${2:?usage: device_train.sh train CONFIG [MINUTES]}
minutes=${3:-8}
out=${OUT:-/tmp/device-out}
mkdir -p "$out"
python3 -m pip install -q --no-deps --no-index .device/wheels/*.whl 2>/dev/null || echo "wheels did not install"
# the package's folders mapped to dadiff.* without installing it (pyproject's package-dir)
shim=$(mktemp -d)
mkdir -p "$shim/dadiff"
: > "$shim/dadiff/__init__.py"
for part in export runtime drone models; do ln -s "$PWD/$part" "$shim/dadiff/$part"; done
export PYTHONPATH="$shim" PYTHONUNBUFFERED=1 DADIFF_DATA_DIR="$PWD/.device/library"
teacher=$( [ -f .device/nanotrack_backbone.onnx ] && python3 -c "import onnxruntime" 2>/dev/null && echo "$PWD/.device" || echo "")
# the GPU run: the same config with a bigger batch, many data workers, the output in /tmp, the teacher carried
python3 - "$config" "$teacher" "${DEVICE_BATCH:-128}" "${DEVICE_WORKERS:-14}" <<'EOF' > /tmp/device-config.toml
import sys
from dadiff.export.train_toml import config_chain, format_toml  # torch-free: follows `extends`
train = {}
for _, own in config_chain(sys.argv[1]):
    train.update(own)
train.update(out="/tmp/device-run", batch_size=int(sys.argv[3]), workers=int(sys.argv[4]))
if sys.argv[2]:
    train["teacher"] = sys.argv[2]
else:
    train.pop("teacher", None)
print(format_toml(train), end="")
EOF
mkdir -p /tmp/device-run
[ -f .device/run/last.pt ] && cp .device/run/last.pt /tmp/device-run/
nvidia-smi --query-gpu=name,memory.total --format=csv,noheader || true
python3 -m dadiff.export.train --config /tmp/device-config.toml --device auto --max-minutes "$minutes" 2>&1 \
    | tr '\r' '\n' | grep -v '^baseline\|^dadiff' | tail -20
cp /tmp/device-run/last.pt /tmp/device-run/log.csv "$out"/
[ -f /tmp/device-run/final.pt ] && cp /tmp/device-run/final.pt "$out"/
[ -f /tmp/device-run/final-ema.pt ] && cp /tmp/device-run/final-ema.pt "$out"/  # the weight average (ema_decay)
ls -la "$out"
