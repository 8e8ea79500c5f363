"""Loading models and checking that the analytic inverse supports them."""

from __future__ import annotations

from pathlib import Path

import mujoco
import numpy as np

from physics.errors import UnsupportedModelError

MODEL_DIR = Path(__file__).parent / "models"


def bundled_models() -> list[str]:
    """Names of the models shipped with physfuse (files `physics/models/NAME.xml`)."""
    return sorted(p.stem for p in MODEL_DIR.glob("*.xml"))


def model_path(name_or_path: str | Path) -> Path:
    """Resolve a bundled model name ("humanoid") or a path to an MJCF file."""
    path = Path(name_or_path)
    if path.suffix == ".xml" and path.is_file():
        return path
    bundled = MODEL_DIR / f"{name_or_path}.xml"
    if bundled.is_file():
        return bundled
    raise UnsupportedModelError(
        f"model {str(name_or_path)!r} is neither an MJCF file nor a bundled model "
        f"(bundled: {', '.join(bundled_models())})"
    )


def load_model(name_or_path: str | Path) -> mujoco.MjModel:
    """Load a bundled model by name or an MJCF file by path."""
    path = model_path(name_or_path)
    try:
        return mujoco.MjModel.from_xml_path(str(path))
    except ValueError as err:
        raise UnsupportedModelError(f"{path}: {err}") from err


def weight(model: mujoco.MjModel) -> float:
    """The model's weight: total mass · |gravity|, N."""
    return float(model.body_subtreemass[0] * np.linalg.norm(model.opt.gravity))
