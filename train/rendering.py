"""Top-down frames of the warehouse (``render_mode="rgb_array"``) and episode animations."""

from __future__ import annotations

import math
from collections.abc import Sequence
from pathlib import Path

import numpy as np
from PIL import Image, ImageDraw, ImageFont

from embedrl.common import atomic_write
from embedrl.train import layout
from embedrl.train.robot import ROBOT_LENGTH
from embedrl.train.world import robot_corners

PIXELS_PER_METRE = 160
"""Frame resolution: the 3.8 m x 1.9 m view becomes 608 x 304 pixels."""
STRIP_FRAMES = 6
"""Frames in a PNG strip: evenly spaced from the start to the end of the episode."""

_BACKGROUND = (245, 245, 240)
_SHELF = (150, 110, 70)
_WALL = (90, 90, 90)
_GOAL = (40, 160, 70)
_ROBOT = (40, 90, 200)
_TRACE = (120, 150, 220)
_OTHER = (200, 90, 40)
_OTHER_TRACE = (230, 160, 120)

Pose = tuple[float, float, float]


def _to_pixel(x: float, y: float) -> tuple[float, float]:
    v = layout.VIEW
    return (x - v.x0) * PIXELS_PER_METRE, (v.y1 - y) * PIXELS_PER_METRE


def draw_frame(
    trajectory: Sequence[Pose],
    moving: Sequence[layout.Rect] = (),
    obstacles: Sequence[layout.Rect] | None = None,
    others: Sequence[Sequence[Pose]] = (),
) -> np.ndarray:
    """An RGB frame (uint8, H x W x 3) of the map, the path so far and the robot at its last pose.

    ``moving`` are obstacles where they are now (the moving shelf), drawn over ``obstacles`` (default: the
    static map, or its fixed part when something moves); ``others`` are further robots' paths.
    """
    if obstacles is None:
        obstacles = layout.FIXED_OBSTACLES if moving else layout.OBSTACLES
    v = layout.VIEW
    size = (round((v.x1 - v.x0) * PIXELS_PER_METRE), round((v.y1 - v.y0) * PIXELS_PER_METRE))
    image = Image.new("RGB", size, _BACKGROUND)
    draw = ImageDraw.Draw(image)
    # Walls last: a moving shelf that is leaving the arena disappears behind them.
    walls = [r for r in obstacles if r in layout.WALLS]
    for rect in (*(r for r in obstacles if r not in layout.WALLS), *moving, *walls):
        colour = _WALL if rect in layout.WALLS else _SHELF
        draw.polygon([_to_pixel(*c) for c in rect.corners], fill=colour)
    gy = _to_pixel(0.0, layout.GOAL_Y)[1]
    draw.line(
        [
            _to_pixel(-layout.GAP_WIDTH / 2, layout.GOAL_Y)[0],
            gy,
            _to_pixel(layout.GAP_WIDTH / 2, layout.GOAL_Y)[0],
            gy,
        ],
        fill=_GOAL,
        width=3,
    )
    for path, colour, trace in ((trajectory, _ROBOT, _TRACE), *((o, _OTHER, _OTHER_TRACE) for o in others)):
        if len(path) > 1:
            draw.line([_to_pixel(x, y) for x, y, _ in path], fill=trace, width=2)
        if path:
            x, y, theta = path[-1]
            c, s = math.cos(theta), math.sin(theta)
            hl = ROBOT_LENGTH / 2
            draw.polygon([_to_pixel(*p) for p in robot_corners(x, y, theta)], fill=colour)
            draw.line([_to_pixel(x, y), _to_pixel(x + c * hl, y + s * hl)], fill=(255, 255, 255), width=3)
    return np.asarray(image)


CAPTION_PX = 16
"""Height of a frame's caption (time and wheel forces) in pixels."""
CAPTION_OUTLINE_PX = 2
"""The white outline of a caption's letters: readable on a light margin and on the walker's floor alike."""


def save_episode(
    frames: Sequence[np.ndarray], path: Path, frame_seconds: float, captions: Sequence[str] | None = None
) -> None:
    """Write frames as an animated GIF (``.gif``) or a PNG strip of ``STRIP_FRAMES`` frames (``.png``),
    each with its caption (the time and the wheel forces) written in its top left corner.

    The file appears complete or not at all (written beside it, then renamed).
    """
    if not frames:
        raise ValueError("no frames to save")
    suffix = path.suffix.lower()
    if suffix not in (".gif", ".png"):
        raise ValueError(f"cannot write {path}: use a .gif (animation) or .png (strip) file name")
    images = [Image.fromarray(f) for f in frames]
    font = ImageFont.load_default(size=CAPTION_PX)
    for image, caption in zip(images, captions or [], strict=False):  # in the light margin under the map
        ImageDraw.Draw(image).text(
            (8, image.height - CAPTION_PX - 12), caption, fill=(0, 0, 0), font=font,
            stroke_width=CAPTION_OUTLINE_PX, stroke_fill=(255, 255, 255),
        )  # fmt: skip
    if suffix == ".gif":
        first, rest = images[0], images[1:]
        atomic_write(
            path,
            lambda tmp: first.save(
                tmp,
                format="GIF",
                save_all=True,
                append_images=rest,
                duration=round(frame_seconds * 1000),
                loop=0,
            ),
        )
        return
    count = min(STRIP_FRAMES, len(images))
    picks = [images[round(i * (len(images) - 1) / max(count - 1, 1))] for i in range(count)]
    w, h = picks[0].size
    strip = Image.new("RGB", (w * count, h), _BACKGROUND)
    for i, im in enumerate(picks):
        strip.paste(im, (i * w, 0))
    atomic_write(path, lambda tmp: strip.save(tmp, format="PNG"))
