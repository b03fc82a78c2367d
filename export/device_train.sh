#!/usr/bin/env bash
# Train on a lent GPU machine (the workplace's `device` tool), resuming a run started here, and bring the
# checkpoint back. That machine has PyTorch, OpenCV and scikit-image but no registry and not this package,
# and takes at most 64 MiB of working tree, so a run goes in two steps. It handles one run folder (one
# config), not a staged recipe: give it a stage's folder and that stage's settings.
#
#   here:   bash export/device_train.sh prepare runs/lite-baseline
#           -> .device/: a 16 MiB library pack, the NanoTrack v3 teacher (used where onnxruntime is there), tqdm,
#              and the run's last.pt (the folder is git-ignored; carry it)
#   device: run(command="bash export/device_train.sh train export/configs/lite-baseline.toml 8",
#               carry=[".device"], timeout_s=600)
#           -> trains for 8 minutes on the GPU (batch and workers scaled up), writes $OUT/last.pt, log.csv;
#              shows dadiff-train's own lines (an error, where it stopped) and exits with its exit code
#   here:   bash export/device_train.sh merge <files_at> runs/lite-baseline
#           -> last.pt (final.pt, final-ema.pt once finished) into the run folder, and the device's log.csv rows
#              appended to its log.csv (replacing rows from the step the device resumed at on);
#              dadiff-train --config ... resumes from it
# RUN_DIR (prepare, merge) is taken from the checkout's root.
set -euo pipefail
cd "$(dirname "$0")/.."
usage="usage: device_train.sh prepare RUN_DIR | train CONFIG [MINUTES] | merge FILES_AT RUN_DIR"
mode=${1:?$usage}

if [ "$mode" = prepare ]; then
    run=${2:?usage: device_train.sh prepare RUN_DIR}
    rm -rf .device && mkdir -p .device/wheels .device/run
    dadiff-eval data pack --output .device/library --max-mib 16
    cp ../shared/weights/nanotrack/v3/nanotrack_backbone.onnx ../shared/weights/nanotrack/v3/nanotrack_head.onnx \
        .device/ 2>/dev/null || echo "no NanoTrack v3 teacher beside the checkout: the device run trains without it"
    python3 -m pip download -q --no-deps --only-binary :all: -d .device/wheels tqdm   # onnxruntime (27 MB) does not fit
    [ -f "$run/last.pt" ] && cp "$run/last.pt" .device/run/
    du -sh .device
    exit 0
fi

if [ "$mode" = merge ]; then
    from=${2:?$usage}
    run=${3:?$usage}
    mkdir -p "$run"
    for name in last.pt final.pt final-ema.pt; do
        if [ -f "$from/$name" ]; then cp "$from/$name" "$run/"; fi
    done
    [ -f "$from/log.csv" ] || { echo "device_train.sh: $from/log.csv: no such file; log not merged"; exit 0; }
    # the run's rows before the device's first step, then the device's, under the run's own header
    python3 - "$from/log.csv" "$run/log.csv" <<'EOF'
import csv, sys
from pathlib import Path
device, local = Path(sys.argv[1]), Path(sys.argv[2])
with open(device, newline="") as f:
    new = list(csv.DictReader(f))
if not new:
    sys.exit(print(f"{device}: no steps; {local} left as it was"))
fields, first, kept = list(new[0]), int(new[0]["step"]), []
if local.exists():
    with open(local, newline="") as f:
        reader = csv.DictReader(f)
        kept = [row for row in reader if int(row["step"]) < first]
        fields = reader.fieldnames or fields
with open(local.with_suffix(".csv.tmp"), "w", newline="") as f:
    writer = csv.DictWriter(f, fieldnames=fields, extrasaction="ignore")
    writer.writeheader()
    writer.writerows(kept + new)
local.with_suffix(".csv.tmp").replace(local)
print(f"{local}: {len(kept)} rows of this run, then {len(new)} of the device's")
EOF
    exit 0
fi

[ "$mode" = train ] || { echo "device_train.sh: error: unknown mode '$mode'" >&2; exit 2; }
config=${2:?$usage}
minutes=${3:-8}
out=${OUT:-/tmp/device-out}
mkdir -p "$out"
tmp=$(mktemp -d)
shim=$(mktemp -d)
trap 'rm -rf "$tmp" "$shim"' EXIT
python3 -m pip install -q --no-deps --no-index .device/wheels/*.whl 2>/dev/null || echo "wheels did not install"
# the package's folders mapped to dadiff.* without installing it (pyproject's package-dir)
mkdir -p "$shim/dadiff"
: > "$shim/dadiff/__init__.py"
for part in export runtime drone models; do ln -s "$PWD/$part" "$shim/dadiff/$part"; done
export PYTHONPATH="$shim" PYTHONUNBUFFERED=1 DADIFF_DATA_DIR="$PWD/.device/library"
teacher=$( [ -f .device/nanotrack_backbone.onnx ] && python3 -c "import onnxruntime" 2>/dev/null && echo "$PWD/.device" || echo "")
# a bad config is one line naming the given file, not the GPU run's copy of it below
python3 -m dadiff.export.train --config "$config" --show-config > /dev/null
# the GPU run: the same config with a bigger batch, many data workers, the output in $tmp, the teacher carried
python3 - "$config" "$teacher" "${DEVICE_BATCH:-128}" "${DEVICE_WORKERS:-14}" "$tmp/run" <<'EOF' > "$tmp/config.toml"
import sys
from dadiff.export.train_toml import config_chain, format_toml  # torch-free: follows `extends`
train = {}
for _, own in config_chain(sys.argv[1]):
    train.update(own)
train.update(out=sys.argv[5], batch_size=int(sys.argv[3]), workers=int(sys.argv[4]))
if sys.argv[2]:
    train["teacher"] = sys.argv[2]
else:
    train.pop("teacher", None)
print(format_toml(train), end="")
EOF
mkdir -p "$tmp/run"
[ -f .device/run/last.pt ] && cp .device/run/last.pt "$tmp/run/"
nvidia-smi --query-gpu=name,memory.total --format=csv,noheader || true
echo "$tmp/config.toml: $config with this machine's batch, workers, out and teacher"
# tqdm's per-step progress lines ("dadiff:  12%|...") dropped; dadiff-train's own lines ("dadiff-train: error: ...",
# "dadiff-train: stopped at step ...") and tracebacks kept
set +e
python3 -m dadiff.export.train --config "$tmp/config.toml" --device auto --max-minutes "$minutes" 2>&1 \
    | tr '\r' '\n' | grep -Ev '^$|^(baseline|dadiff): +[0-9]+%' | tail -20
code=${PIPESTATUS[0]}
set -e
for name in last.pt log.csv final.pt final-ema.pt; do  # final-ema.pt: the weight average (ema_decay)
    if [ -f "$tmp/run/$name" ]; then cp "$tmp/run/$name" "$out"/; fi
done
ls -la "$out"
exit "$code"
