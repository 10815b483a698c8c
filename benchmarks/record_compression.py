"""Lossless compression for long takes: bytes per frame and CPU per frame at 1280x720, PNG as
`rig record --compress png` writes it (PyAV's PNG encoder, rig/storage/png.py) and, for comparison,
FFV1 (PyAV, one intra frame per packet), on simulator frames with the sensor's noise and without it
(real cameras' noise is what limits any lossless codec). CPU is the encoding thread's own time.

    .venv/bin/python benchmarks/record_compression.py [--frames 6] [--json]
"""
from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from rig.storage.png import PngEncoder, read_png  # noqa: E402

W, H = 1280, 720


def frames(n: int, noise: bool) -> list[np.ndarray]:
    from simulator.takes import TakeRenderer
    from simulator.variety import draw_variety

    r = TakeRenderer(draw_variety(0), (W, H), n_cameras=2, noise=noise)
    return [r.image("left", r.scene_time(3 * i, 30.0), i) for i in range(n)]


def png(images: list[np.ndarray], tmp: Path) -> dict:
    enc = PngEncoder(W, H, 3, 1)
    sizes, cpu = [], 0.0
    for i, img in enumerate(images):
        t0 = time.thread_time()
        data = enc.encode(img)
        cpu += time.thread_time() - t0
        sizes.append(len(data))
        path = tmp / f"{i}.png"
        path.write_bytes(data)
        t0 = time.thread_time()
        back = read_png(path)
        decode = time.thread_time() - t0
        assert np.array_equal(back, img), "PNG must be lossless"
    return {"bytes_per_frame": int(np.mean(sizes)), "encode_ms_per_frame": round(1e3 * cpu / len(images), 1),
            "decode_ms_per_frame": round(1e3 * decode, 1)}


def ffv1(images: list[np.ndarray]) -> dict:
    import av

    cc = av.CodecContext.create("ffv1", "w")
    cc.width, cc.height, cc.pix_fmt = W, H, "bgr0"
    cc.options = {"level": "3", "coder": "0", "slices": "4", "slicecrc": "1", "g": "1"}
    cc.thread_count = 1
    sizes, cpu = [], 0.0
    for img in images:
        t0 = time.thread_time()
        frame = av.VideoFrame.from_ndarray(img, format="rgb24").reformat(format="bgr0")
        packets = list(cc.encode(frame))
        cpu += time.thread_time() - t0
        sizes.append(sum(p.size for p in packets))
    sizes += [sum(p.size for p in cc.encode(None))]  # whatever the encoder held back
    return {"bytes_per_frame": int(sum(sizes) / len(images)), "encode_ms_per_frame": round(1e3 * cpu / len(images), 1)}


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--frames", type=int, default=6)
    ap.add_argument("--json", action="store_true")
    args = ap.parse_args()
    import tempfile

    raw = W * H * 3
    result = {"frame": f"{W}x{H} RGB8", "raw_bytes_per_frame": raw, "cases": {}}
    with tempfile.TemporaryDirectory() as tmp:
        for noise in (True, False):
            images = frames(args.frames, noise)
            case = {"png": png(images, Path(tmp)), "ffv1": ffv1(images)}
            for c in case.values():
                c["ratio"] = round(raw / c["bytes_per_frame"], 2)
            result["cases"]["sensor noise" if noise else "no noise"] = case
    if args.json:
        print(json.dumps(result))
        return 0
    for name, case in result["cases"].items():
        for codec, c in case.items():
            dec = f", decode {c['decode_ms_per_frame']} ms" if "decode_ms_per_frame" in c else ""
            print(f"{name:13s} {codec:5s}: {c['bytes_per_frame'] / 1e6:.2f} MB per frame ({c['ratio']:.2f} x smaller than "
                  f"{raw / 1e6:.2f} MB raw), encode {c['encode_ms_per_frame']} ms of CPU per frame{dec}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
