#!/usr/bin/env bash
# Idempotent set-up: system libraries, .venv, the project and its dependencies.
# Fast when nothing changed: a stamp records the hash of pyproject.toml.
set -euo pipefail
cd "$(dirname "$0")/.."

PYTHON=${PYTHON:-python3}
VENV=.venv
STAMP=$VENV/.setup-stamp

ensure_system_library() {  # $1 = soname, $2 = Debian package
    if ldconfig -p 2>/dev/null | grep -q "$1"; then return 0; fi
    echo "setup: installing system library $2 (needed by Open3D)"
    local sudo=""
    if [ "$(id -u)" != 0 ]; then
        if command -v sudo >/dev/null; then sudo="sudo"; else
            echo "setup: error: $1 is missing and we are not root; install the Debian package $2" >&2
            exit 1
        fi
    fi
    $sudo apt-get update -qq
    DEBIAN_FRONTEND=noninteractive $sudo apt-get install -y -qq "$2" >/dev/null
}

ensure_system_library libusb-1.0.so.0 libusb-1.0-0
ensure_system_library libgomp.so.1 libgomp1

# --browser: Debian's Chromium, for the test that renders the comparison report
if [ "${1:-}" = "--browser" ] && ! command -v chromium >/dev/null; then
    echo "setup: installing Chromium (renders the comparison report in a test)"
    sudo=""; [ "$(id -u)" != 0 ] && sudo="sudo"
    { $sudo apt-get update -qq && DEBIAN_FRONTEND=noninteractive $sudo apt-get install -y -qq chromium >/dev/null; } \
        || echo "setup: warning: Chromium did not install; the report screenshot test will skip" >&2
fi

# the raster forest the fusion uses on clouds without training labels: trained once on the
# synthetic city (about 20 s) into the user's cache, not at run time by the fusion
train_raster_forest() {
    "$VENV/bin/python" -m data_samples.raster_forest \
        || { echo "setup: error: training the raster forest failed (see above)" >&2; exit 1; }
}

want=$(sha256sum pyproject.toml | cut -d' ' -f1)
if [ -f "$STAMP" ] && [ "$(cat "$STAMP")" = "$want" ] && "$VENV/bin/python" -c "import open3d, workbench" 2>/dev/null; then
    train_raster_forest
    exit 0
fi

if [ ! -x "$VENV/bin/python" ]; then
    echo "setup: creating $VENV with $("$PYTHON" --version)"
    "$PYTHON" -m venv "$VENV"
fi
echo "setup: installing the workbench and its dependencies into $VENV"
"$VENV/bin/python" -m pip install -q --upgrade pip 2>&1 | grep -v "^WARNING: Location" || true
"$VENV/bin/python" -m pip install -q -e ".[dev]" 2>&1 | grep -v "^WARNING: Location" || true
"$VENV/bin/python" -c "import open3d, maxflow, rasterio, laspy, shapely, skimage, sklearn, cv2, distributed, workbench" \
    || { echo "setup: error: the installed packages do not import (see above)" >&2; exit 1; }
echo "$want" > "$STAMP"
train_raster_forest
echo "setup: done"
