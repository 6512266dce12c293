"""Render a report page in headless Chromium and save a full-page screenshot.

    python scripts/screenshot.py REPORT/report.html OUT.png [--width 1400] [--height 6000]

Needs Chromium (`make report-check` installs Debian's package). The page is opened from
the file system with networking off, so it shows only what it embeds.
"""

from __future__ import annotations

import argparse
import shutil
import subprocess
import sys
import tempfile
from pathlib import Path

FLAGS = [
    "--headless",
    "--no-sandbox",
    "--disable-gpu",
    "--disable-quic",
    "--no-first-run",
    "--disable-background-networking",
    "--disable-component-update",
    "--disable-sync",
    "--hide-scrollbars",
]


def chromium() -> str | None:
    for name in ("chromium", "chromium-browser", "google-chrome"):
        path = shutil.which(name)
        if path:
            return path
    return None


def screenshot(page: Path, out: Path, width: int = 1400, height: int = 6000) -> None:
    exe = chromium()
    if exe is None:
        raise SystemExit("screenshot: Chromium not found (make report-check installs it)")
    with tempfile.TemporaryDirectory() as profile:
        cmd = [
            exe,
            *FLAGS,
            f"--user-data-dir={profile}",
            f"--window-size={width},{height}",
            f"--screenshot={out.absolute()}",
            page.absolute().as_uri(),
        ]
        subprocess.run(cmd, check=True, capture_output=True, timeout=120)
    if not out.exists():
        raise SystemExit(f"screenshot: Chromium wrote no {out}")


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("page", type=Path)
    p.add_argument("out", type=Path)
    p.add_argument("--width", type=int, default=1400)
    p.add_argument("--height", type=int, default=6000)
    a = p.parse_args()
    screenshot(a.page, a.out, a.width, a.height)
    print(f"wrote {a.out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
