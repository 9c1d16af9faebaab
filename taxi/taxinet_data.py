"""Labelled TaxiNet images: uniformly sampled states and their wing-camera frames."""

import numpy as np

from reachwatch.diagrams import StateRenderer

#: Where TaxiNet is trained: px (m), py (m), theta (deg). py reaches past the paper
#: grid's [100, 250] m so the 8 s rollouts (40 m further) stay in distribution.
TRAINING_BOX = {"px": (-11.0, 11.0), "py": (80.0, 320.0), "theta_deg": (-28.0, 28.0)}


def sample_states(n: int, rng: np.random.Generator, box=None) -> np.ndarray:
    """``(n, 3)`` states [px m, py m, theta rad] uniform in ``box`` (degrees for theta)."""
    box = box or TRAINING_BOX
    (a, b), (c, d), (e, f) = box["px"], box["py"], box["theta_deg"]
    return np.column_stack([rng.uniform(a, b, n), rng.uniform(c, d, n),
                            np.deg2rad(rng.uniform(e, f, n))])


def render_states(renderer: StateRenderer, states, progress=None) -> np.ndarray:
    """``(n, H, W, 3)`` uint8 images of ``states`` (one reused Context)."""
    states = np.asarray(states, dtype=float).reshape(-1, 3)
    config = renderer.world.camera_config
    images = np.empty((len(states), config.height, config.width, 3), np.uint8)
    for i in (progress(range(len(states))) if progress else range(len(states))):
        images[i] = renderer.render(states[i])
    return images


def targets(states) -> np.ndarray:
    """TaxiNet targets [px m, theta deg] of ``states`` [px m, py m, theta rad]."""
    states = np.asarray(states)
    return np.column_stack([states[:, 0], np.rad2deg(states[:, 2])]).astype(np.float32)
