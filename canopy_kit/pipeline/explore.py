"""Open a field session for interactive exploration (what the notebooks call first)."""

from __future__ import annotations

from pathlib import Path
from typing import Any

from canopy_kit.config import load_preset
from canopy_kit.errors import InputError
from canopy_kit.io.session_layout import drone_dir, find_bag, truth_dir


def session_paths(session: str | Path) -> dict[str, Path | None]:
    """Bag, drone folder and truth folder of a session folder (simulated or laid out alike)."""
    root = Path(session)
    if not root.is_dir():
        raise InputError(f"{root}: session folder does not exist")
    drone = drone_dir(root)
    truth = truth_dir(root)
    return {
        "bag": find_bag(root),
        "drone": drone if drone.is_dir() else None,
        "truth": root if truth.is_dir() else None,
    }


def load_context(
    session: str | Path | None = None,
    bag: str | Path | None = None,
    run_dir: str | Path | None = None,
    preset: str = "adaptive",
    use_drone: bool = True,
    progress: Any = None,
) -> Any:
    """Every stage's result for a session (cached in ``run_dir/.cache``), as a RunContext.

    Give a session folder (bag + optional ``drone/`` and ``truth/``) or a bag alone.
    """
    from canopy_kit.pipeline import compute

    if session is None and bag is None:
        raise InputError("give a session folder or a bag")
    paths = (
        session_paths(session)
        if session is not None
        else {"bag": Path(bag), "drone": None, "truth": None}
    )
    run_dir = Path(run_dir) if run_dir is not None else Path(paths["bag"]).parent / "notebook_run"
    ctx, _ = compute(
        load_preset(preset),
        paths["bag"],
        run_dir,
        drone_images=paths["drone"] if use_drone else None,
        truth=paths["truth"],
        progress=progress,
    )
    return ctx
