"""A labelled grid of wing-camera images over runways x hours x skies."""

import cv2
import numpy as np

from reachwatch.systems import RUNWAYS, SKIES, CameraConfig, Environment

from .render import StateRenderer

DEFAULT_HOURS = (9.0, 17.0, 21.0)


def contact_sheet(*, state=(0.0, 150.0, 0.0), camera: CameraConfig = None,
                  runways=tuple(RUNWAYS), hours=DEFAULT_HOURS, skies=SKIES,
                  progress=None) -> np.ndarray:
    """RGB uint8 grid: one row per runway, one column per (hour, sky), each tile
    captioned. ``state = [px m, py m, theta rad]``; ``progress`` wraps the iterable."""
    tiles, combos = [], [(h, s) for h in hours for s in skies]
    jobs = [(r, h, s) for r in runways for h, s in combos]
    for runway, hour, sky in (progress(jobs) if progress else jobs):
        env = Environment(runway, hour, sky)
        image = StateRenderer(environment=env, camera=camera).render(state)
        tile = np.ascontiguousarray(image)
        cv2.putText(tile, f"{runway} {hour:g}h {sky}", (4, 14), cv2.FONT_HERSHEY_SIMPLEX,
                    0.4, (255, 0, 255), 1, cv2.LINE_AA)
        tiles.append(tile)
    rows = [np.hstack(tiles[i:i + len(combos)]) for i in range(0, len(tiles), len(combos))]
    return np.vstack(rows)
