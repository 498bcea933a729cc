#!/usr/bin/env bash
# Screenshot of the rerun viewer showing a run, rendered on the CPU (no GPU, no screen needed).
#
#   scripts/screenshot_viewer.sh [SCENARIO] [OUT.png]      (defaults: denver_trail results/rerun_viewer_native.png)
#
# Runs `pancam-graph run SCENARIO --rerun save` and opens the recording in rerun's native
# viewer on a virtual X display (Xvfb); wgpu renders with Mesa's llvmpipe through Vulkan
# (lavapipe) and the viewer's own --screenshot-to writes the PNG. Map tiles need the internet:
# offline, the map view shows the GPS fixes and the estimate on a blank background.
# Needs Debian's xvfb and mesa-vulkan-drivers (installed here with apt-get when missing).
set -euo pipefail
cd "$(dirname "$0")/.."
scenario="${1:-denver_trail}"
png="${2:-results/rerun_viewer_native.png}"

if ! command -v xvfb-run >/dev/null || ! ls /usr/share/vulkan/icd.d/lvp_icd*.json >/dev/null 2>&1; then
    apt-get install -y --no-install-recommends xvfb xauth mesa-vulkan-drivers >/dev/null
fi
./dev.sh setup >/dev/null
work="$(mktemp -d)"
trap 'rm -rf "$work"' EXIT
.venv/bin/pancam-graph run "$scenario" --out "$work/run" --quiet --rerun save >/dev/null 2>&1
# A screen larger than the window keeps Xvfb's pointer (at the screen centre) off the window,
# so no hover tooltip is drawn.
xvfb-run -a -s "-screen 0 3840x2160x24" \
    .venv/bin/rerun "$work/run/recording.rrd" --window-size 1600x900 --screenshot-to "$work/shot.png" \
    >"$work/viewer.log" 2>&1 || { cat "$work/viewer.log"; exit 1; }
# The viewer writes at 2x scale; halve it and use a 256-colour palette to keep the committed PNG small.
.venv/bin/python - "$work/shot.png" "$png" <<'PY'
import sys
from PIL import Image
image = Image.open(sys.argv[1]).convert("RGB")
image = image.resize((image.width // 2, image.height // 2), Image.LANCZOS)
image.quantize(colors=256, method=Image.Quantize.FASTOCTREE).save(sys.argv[2], optimize=True)
PY
echo "screenshot: $png"
