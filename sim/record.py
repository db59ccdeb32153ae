"""`toptag sim record`: one RSU camera's rendered frames as a video file, with a truth file beside it.

    toptag sim record --out drive.mp4 --rsu rsu-sw [--scenario FILE] [--start 9.5] [--duration 8]
                      [--fps 10] [--codec h264|mp4v] [--crf 18] [--images DIR]

Plays a scenario (default: the bundled demo) from --start seconds for --duration seconds and renders
what the RSU's camera sees at its frame rate, with the scenario's image model except its codec step: the
video codec takes its place, as on a real IP camera. Codecs:
    h264   H.264 (libx264, main profile, no B-frames, a key frame every second, constant quality --crf),
           what IP cameras stream; encoded by the `ffmpeg` program (Debian's ffmpeg has libx264;
           opencv-python-headless cannot encode H.264).
    mp4v   MPEG-4 part 2 through OpenCV alone (no ffmpeg needed; a fallback, not what cameras send).
Writes FILE and FILE's stem + ".truth.json": the camera file, the vehicle files, the image model, the
frame rate and per frame its index, capture time (t_ns: scenario time, ns, frame 0 at --start) and every
bus on the road with its true pose (x, y, yaw, roof z) and the tags whose plates are in view.
--images DIR also writes every frame losslessly as DIR/frame-NNNNN.png (the same frames as images).
"""
from __future__ import annotations

import argparse
import json
import shutil
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

from sim.render import render
from sim.scenario import bundled_scenario_path, load_scenario
from sim.world import World
from toptag.errors import InputError, report
from toptag.units import NS_PER_S

CODECS = ("h264", "mp4v")


class VideoWriterError(InputError):
    """The video cannot be written (codec or encoder missing, disk)."""


def truth_path(video: str | Path) -> Path:
    v = Path(video)
    return v.with_name(v.stem + ".truth.json")


class GrayVideoWriter:
    """Gray uint8 frames to a video file: H.264 through the ffmpeg program, or MPEG-4 part 2 (OpenCV)."""

    def __init__(self, path: Path, width: int, height: int, fps: float, codec: str = "h264", crf: int = 18):
        self.path, self.codec = Path(path), codec
        self.size = (width, height)
        self._proc = self._cv = None
        if codec == "h264":
            exe = shutil.which("ffmpeg")
            if exe is None:
                raise VideoWriterError("--codec h264 needs the ffmpeg program (Debian: apt-get install ffmpeg); "
                                       "--codec mp4v needs nothing else")
            gop = max(1, int(round(fps)))
            cmd = [exe, "-hide_banner", "-loglevel", "error", "-y", "-f", "rawvideo", "-pix_fmt", "gray",
                   "-s", f"{width}x{height}", "-framerate", f"{fps:g}", "-i", "-",
                   "-c:v", "libx264", "-profile:v", "main", "-pix_fmt", "yuv420p", "-crf", str(int(crf)),
                   "-preset", "medium", "-g", str(gop), "-bf", "0", "-movflags", "+faststart", str(self.path)]
            self._proc = subprocess.Popen(cmd, stdin=subprocess.PIPE, stderr=subprocess.PIPE)
        elif codec == "mp4v":
            import cv2

            self._cv = cv2.VideoWriter(str(self.path), cv2.VideoWriter_fourcc(*"mp4v"), fps, (width, height), False)
            if not self._cv.isOpened():
                raise VideoWriterError(f"video {self.path}: OpenCV cannot write MPEG-4 there")
        else:
            raise VideoWriterError(f"codec {codec!r}: known codecs are {', '.join(CODECS)}")

    def write(self, gray: np.ndarray) -> None:
        if gray.shape != (self.size[1], self.size[0]) or gray.dtype != np.uint8:
            raise ValueError(f"frame {gray.shape} {gray.dtype}: expected {self.size[1]}x{self.size[0]} uint8")
        if self._proc is not None:
            try:
                self._proc.stdin.write(np.ascontiguousarray(gray).tobytes())
            except BrokenPipeError:
                raise VideoWriterError(f"video {self.path}: ffmpeg stopped: {self._stderr()}") from None
        else:
            self._cv.write(gray)

    def _stderr(self) -> str:
        try:
            return self._proc.stderr.read().decode(errors="replace").strip().splitlines()[-1]
        except (IndexError, OSError, ValueError):
            return "no message"

    def close(self) -> None:
        if self._proc is not None:
            self._proc.stdin.close()
            if self._proc.wait() != 0:
                raise VideoWriterError(f"video {self.path}: ffmpeg failed: {self._stderr()}")
            self._proc = None
        elif self._cv is not None:
            self._cv.release()
            self._cv = None


def record(world: World, rsu_id: str, out: Path, start_s: float, duration_s: float, fps: float | None = None,
           codec: str = "h264", crf: int = 18, images: Path | None = None, progress=None) -> dict:
    """Render and encode; returns the truth document (also written beside the video)."""
    camera = world.camera(rsu_id)
    fps = float(fps or world.fps[world.rsu_ids.index(rsu_id)])
    # The recorder's encoder is the stream's codec: the image model's own codec step is left out.
    model = world.model.model_copy(update={"codec": "jpeg", "jpeg_quality": 0})
    n = max(1, int(round(duration_s * fps)))
    rng = np.random.default_rng([world.scenario.seed, 99])
    out.parent.mkdir(parents=True, exist_ok=True)
    if images is not None:
        images.mkdir(parents=True, exist_ok=True)
    writer = GrayVideoWriter(out, camera.width, camera.height, fps, codec, crf)
    frames = []
    t_start = time.monotonic()
    try:
        for k in range(n):
            t_ns = int(round((start_s + k / fps) * NS_PER_S))
            gray = render(camera, world.vehicles_at(t_ns), world.occluders_at(t_ns), model, rng)
            writer.write(gray)
            if images is not None:
                import cv2

                cv2.imwrite(str(images / f"frame-{k:05d}.png"), gray)
            in_view = world.tags_in_view(rsu_id, t_ns)
            frames.append({"frame": k, "t_ns": t_ns, "pts_s": k / fps, "vehicles": {
                bus: {"x": s.x, "y": s.y, "yaw": s.yaw, "z": s.z, "tags_in_view": in_view.get(bus, [])}
                for bus, s in world.truth_at(t_ns).items()}})
            if progress is not None and (k + 1) % max(1, n // 10) == 0:
                progress(f"{k + 1}/{n} frames ({time.monotonic() - t_start:.0f} s)")
    finally:
        writer.close()
    doc = {"video": out.name, "rsu": rsu_id, "codec": codec, "crf": crf if codec == "h264" else None, "fps": fps,
           "start_s": start_s, "t_ns_of": "scenario time of the frame's capture; frame k at start_s + k / fps",
           "image_model": model.describe().replace("no JPEG", f"{codec} video instead of JPEG"),
           "camera": camera.to_model().model_dump(exclude_none=True),
           "vehicles": {b: world.vehicle(b).to_dict() for b in world.bus_ids},
           "frames": frames}
    truth_path(out).write_text(json.dumps(doc, indent=1))
    return doc


def main(argv: list[str]) -> int:
    p = argparse.ArgumentParser(prog="toptag sim record", description=__doc__.split("\n\n")[0])
    p.add_argument("--out", required=True, type=Path, metavar="FILE.mp4")
    p.add_argument("--rsu", required=True, help="the RSU (camera id) whose view is recorded")
    p.add_argument("--scenario", default=None, metavar="FILE", help="scenario file (default: the bundled demo)")
    p.add_argument("--start", type=float, default=9.5, help="scenario time of the first frame, s (default 9.5: "
                                                           "bus-17 turning in rsu-sw's view)")
    p.add_argument("--duration", type=float, default=8.0, help="seconds of video (default 8)")
    p.add_argument("--fps", type=float, default=None, help="frames per second (default: the scenario's)")
    p.add_argument("--codec", choices=CODECS, default="h264")
    p.add_argument("--crf", type=int, default=18, help="H.264 constant quality, lower is better (default 18)")
    p.add_argument("--images", type=Path, default=None, metavar="DIR", help="also write every frame as a PNG")
    args = p.parse_args(argv)
    try:
        scenario = load_scenario(args.scenario or bundled_scenario_path())
        world = World(scenario)
        if args.rsu not in world.rsu_ids:
            raise InputError(f"--rsu {args.rsu}: not in the scenario (its RSUs: {', '.join(world.rsu_ids)})")
        if not args.duration > 0 or args.start < 0:
            raise InputError("--duration must be positive and --start not negative")
        world.start(0)
        doc = record(world, args.rsu, args.out, args.start, args.duration, args.fps, args.codec, args.crf,
                     args.images, progress=lambda m: print(f"toptag sim record: {m}", file=sys.stderr))
    except InputError as e:
        return report("sim record", e)
    seen = sum(1 for f in doc["frames"] if any(v["tags_in_view"] for v in f["vehicles"].values()))
    print(f"{args.out}: {len(doc['frames'])} frames at {doc['fps']:g} fps ({args.codec}), a tag in view in {seen}; "
          f"truth in {truth_path(args.out)}")
    return 0
