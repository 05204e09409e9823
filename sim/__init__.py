"""sim: the virtual experiment, where the truth is known.

Scenes (TOML dataclasses, the paper's two as presets) are meshed with gmsh, compressed with a
scikit-fem neo-Hookean model, projected exactly onto the C7942 grid and exposed on a model panel
into the same experiment files the lab writes, with the ground truth beside the frames.

The public API, importable from ``sim`` directly::

    load_scene(name_or_toml) -> Scene       block_scene(size_mm=10, E_kpa=5, nu=0.45) -> Scene
    compress(scene, ratios=None) -> [State] project(scene, state) -> float32 (rows, cols)
    truth_displacement(scene, fixed, moving) simulate_experiment(scene, "sim.h5")

Submodules are imported on first use, so ``import sim`` stays cheap.
"""

from __future__ import annotations

import importlib

__all__ = [
    "load_scene",
    "block_scene",
    "Scene",
    "compress",
    "State",
    "ConvergenceError",
    "project",
    "truth_displacement",
    "simulate_experiment",
]

_WHERE = {
    "load_scene": "sim.scene",
    "block_scene": "sim.scene",
    "Scene": "sim.scene",
    "compress": "sim.mechanics",
    "State": "sim.mechanics",
    "ConvergenceError": "sim.mechanics",
    "project": "sim.xray",
    "truth_displacement": "sim.truth",
    "simulate_experiment": "sim.lab",
}


def __getattr__(name):
    if name in _WHERE:
        value = getattr(importlib.import_module(_WHERE[name]), name)
        globals()[name] = value
        return value
    raise AttributeError(f"module 'sim' has no attribute {name!r}")


def __dir__():
    return sorted(list(globals()) + __all__)
