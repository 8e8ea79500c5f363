"""A picture of a Rerun recording at one time, from a headless Rerun Viewer (software
rendering: no screen or GPU needed; `XDG_RUNTIME_DIR` must name a writable folder).

    physfuse diagnose recordings/humanoid_push.mcap --config configs/humanoid_push.toml \\
        --out out/humanoid_push_diagnose
    XDG_RUNTIME_DIR=/tmp .venv/bin/python docs/images/rerun_screenshot.py \\
        out/humanoid_push_diagnose/diagnostics.rrd 1.05 docs/images/diagnose_humanoid_push.png
"""

from __future__ import annotations

import argparse
import shutil
import sys
import time
from pathlib import Path

from rerun.experimental import ViewerClient


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("recording", type=Path, help=".rrd file")
    parser.add_argument("time_s", type=float, help="the time cursor, s on the 'time' timeline")
    parser.add_argument("png", type=Path)
    parser.add_argument("--port", type=int, default=9877, help="the viewer's gRPC port")
    args = parser.parse_args()
    executable = shutil.which("rerun", path=str(Path(sys.executable).parent))
    viewer = ViewerClient.spawn(
        headless=True, port=args.port, hide_welcome_screen=True, executable_path=executable
    )
    try:
        viewer.open(args.recording.resolve().as_uri())
        viewer.set_time("time", duration=args.time_s, play_state="paused")
        time.sleep(2.0)  # the views' first paint at the new time
        viewer.save_screenshot(str(args.png.resolve()))
    finally:
        viewer.quit()


if __name__ == "__main__":
    main()
