"""Times lerobot's own video encoders on the frames recorder-bench wrote, with the same settings.

Usage: python lerobot_encode.py FRAMES.rgb WIDTH HEIGHT FPS VCODEC
Prints one JSON line: {"streaming_fps": ..., "png_path_fps": ..., "frames": N}
- streaming: lerobot.datasets.video_utils.StreamingVideoEncoder fed numpy frames (lerobot's in-recording
  path, one encoder thread per camera, PyAV) — the like-for-like comparison;
- png_path: encode_video_frames over a directory of PNGs (lerobot's classic save_episode path; includes
  PNG decoding, excludes writing the PNGs).
"""

import json
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
from PIL import Image

from lerobot.datasets.video_utils import encode_video_frames

path, w, h, fps, vcodec = sys.argv[1], int(sys.argv[2]), int(sys.argv[3]), int(sys.argv[4]), sys.argv[5]
frames = np.fromfile(path, dtype=np.uint8).reshape(-1, h, w, 3)
n = len(frames)
out = {"frames": n}
with tempfile.TemporaryDirectory() as tmp:
    tmp = Path(tmp)
    try:
        from lerobot.datasets.video_utils import StreamingVideoEncoder

        enc = StreamingVideoEncoder(fps=fps, vcodec=vcodec, pix_fmt="yuv420p", g=2, crf=30, queue_maxsize=n + 1)
        t0 = time.perf_counter()
        enc.start_episode(["cam"], tmp)
        for f in frames:
            enc.feed_frame("cam", f)
        enc.finish_episode()
        out["streaming_fps"] = n / (time.perf_counter() - t0)
        enc.close()
    except ImportError:
        out["streaming_fps"] = None
    imgs = tmp / "imgs"
    imgs.mkdir()
    for i, f in enumerate(frames):
        Image.fromarray(f).save(imgs / f"frame-{i:06d}.png", compress_level=1)
    t0 = time.perf_counter()
    encode_video_frames(imgs, tmp / "out.mp4", fps, vcodec=vcodec, g=2, crf=30, overwrite=True)
    out["png_path_fps"] = n / (time.perf_counter() - t0)
print(json.dumps(out))
