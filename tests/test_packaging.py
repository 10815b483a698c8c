"""The wheel carries the shipped model, so that an installation that is not editable serves it: the
package data `inference/runtime/models` (a link to models/ in the source tree) that
inference.runtime.shipped reads."""
from __future__ import annotations

import shutil
import subprocess
import sys
import zipfile
import zlib
from pathlib import Path

from inference.runtime import shipped

REPO = Path(__file__).resolve().parents[1]
PACKAGES = ("common", "calibration", "sync", "simulator", "inference", "rig")
SHIPPED = ("*.onnx", "*.data", "*.pt", "MODEL_CARD.md")  # what the model folder ships (pyproject's package-data)


def test_the_wheel_carries_the_shipped_model(tmp_path):
    # built from a copy of the tree, so that the build's own folders (build/, *.egg-info) stay out of the checkout
    src = tmp_path / "src"
    src.mkdir()
    for name in ("pyproject.toml", "README.md", "LICENSE"):
        shutil.copy2(REPO / name, src / name)
    for pkg in PACKAGES:
        shutil.copytree(REPO / pkg, src / pkg, symlinks=True, ignore=shutil.ignore_patterns("__pycache__"))
    shutil.copytree(REPO / "models", src / "models")
    subprocess.run([sys.executable, "-m", "pip", "wheel", "--no-deps", "--no-build-isolation", "--no-index", "-q",
                    "-w", str(tmp_path / "dist"), str(src)], check=True, timeout=300)
    wheel, = (tmp_path / "dist").glob("rig-*.whl")
    with zipfile.ZipFile(wheel) as z:
        packed = {Path(i.filename).name: i.CRC for i in z.infolist() if i.filename.startswith("inference/runtime/models/")}
    ours = sorted({p for pattern in SHIPPED for p in (REPO / "models").glob(pattern)})
    assert {p.name for p in ours} >= {f"{shipped.NAME}.onnx", f"{shipped.NAME}.pt", f"{shipped.LIVE_NAME}.onnx"}
    assert sorted(packed) == [p.name for p in ours]
    for p in ours:  # the same bytes as the folder the source tree runs from
        assert packed[p.name] == zlib.crc32(p.read_bytes()), p.name
