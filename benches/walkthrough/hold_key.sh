#!/usr/bin/env bash
# Holds a movement key in a real `sylva view` window, as a user does, and counts the
# frames the window showed while the key was down (each shown frame is written by
# --frames-out; a frame counts when its file was written between key-down and key-up).
#
# Usage: benches/walkthrough/hold_key.sh [SCENE=meadow] [SECONDS=3] [KEY=w] [view flags...]
# Needs Xvfb, xdotool and ImageMagick (apt-get install xvfb xdotool imagemagick) and a
# release build (SYLVA=target/release/sylva by default). Prints one line: frames shown
# while held, their rate, the delay from key-down to the first frame showing a new view
# (a quarter of its pixels changed from the last frame before the key; a frame that was
# refining the resting view may still appear first), and from key-up to the next frame.
set -euo pipefail
SCENE=${1:-meadow}; HOLD=${2:-3}; KEY=${3:-w}; shift $(( $# < 3 ? $# : 3 )) || true
SYLVA=${SYLVA:-target/release/sylva}
OUT=$(mktemp -d)
trap 'kill $VIEW $XVFB 2>/dev/null || true; rm -rf "$OUT"' EXIT
DISPLAY_NUMBER=${DISPLAY_NUMBER:-77}
Xvfb ":$DISPLAY_NUMBER" -screen 0 800x600x24 >/dev/null 2>&1 & XVFB=$!
export DISPLAY=":$DISPLAY_NUMBER"
sleep 1
mkdir -p "$OUT/frames"
"$SYLVA" view --scene "$SCENE" --width 640 --height 480 --threads 2 \
  --frames-out "$OUT/frames" "$@" >"$OUT/view.log" 2>&1 & VIEW=$!
for _ in $(seq 1 600); do [ -n "$(ls "$OUT/frames")" ] && break; sleep 0.1; done
sleep 1.5
WINDOW=$(xdotool search --sync --onlyvisible --name sylva | head -1)
xdotool windowactivate --sync "$WINDOW" 2>/dev/null || true
xdotool windowfocus --sync "$WINDOW"
date +%s.%N >"$OUT/down"
xdotool keydown --window "$WINDOW" "$KEY"
sleep "$HOLD"
xdotool keyup --window "$WINDOW" "$KEY"
date +%s.%N >"$OUT/up"
sleep 3
python3 - "$OUT" "$SCENE" <<'PY'
import os, sys
out, scene = sys.argv[1], sys.argv[2]
down = float(open(f"{out}/down").read()); up = float(open(f"{out}/up").read())
import subprocess
frames = sorted((os.path.getmtime(os.path.join(out, "frames", f)), os.path.join(out, "frames", f))
                for f in os.listdir(f"{out}/frames"))
held = [(t, f) for t, f in frames if down <= t <= up]
before = [f for t, f in frames if t < down]
after = [t for t, f in frames if t > up]
def changed(a, b):
    # Pixels that differ by more than 10 %, as a share of the image.
    r = subprocess.run(["compare", "-metric", "AE", "-fuzz", "10%", a, b, "null:"],
                       capture_output=True, text=True)
    w, h = map(int, subprocess.run(["identify", "-format", "%w %h", a],
                                   capture_output=True, text=True).stdout.split())
    return float(r.stderr.split()[0]) / (w * h)
new_view = next((t for t, f in held if before and changed(before[-1], f) > 0.25), None)
first = f"{(new_view - down) * 1e3:.0f} ms" if new_view else "none"
release = f"{(after[0] - up) * 1e3:.0f} ms" if after else "none"
print(f"{scene}: {len(held)} frames shown while the key was held {up - down:.2f} s "
      f"({len(held) / (up - down):.1f}/s); first new view {first} after key-down; "
      f"next frame {release} after key-up")
PY
