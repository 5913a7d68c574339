"""Scene sets (models/scenes/*.json) and the rule that keeps selection honest: train, validation and
test share no scene. Two scenes are the same scene when they share a trajectory seed or a name,
or when they share port and background with Sun elevations closer than SUN_MARGIN_DEG (the same
view under nearly the same light)."""

from __future__ import annotations

from pathlib import Path

from oibar_hil.dataset import DatasetError, SequenceSpec, load_spec_file

from .config import ConfigError

SUN_MARGIN_DEG = 10.0


def load_set(path: str | Path) -> list[SequenceSpec]:
    try:
        return load_spec_file(Path(path))
    except DatasetError as exc:
        raise ConfigError(str(exc)) from exc


def _clash(a: SequenceSpec, b: SequenceSpec) -> str | None:
    if a.name == b.name:
        return "same name"
    if a.seed == b.seed:
        return f"same trajectory seed {a.seed}"
    if (
        a.port == b.port
        and a.background == b.background
        and abs(a.sun_elevation_deg - b.sun_elevation_deg) < SUN_MARGIN_DEG
    ):
        return (
            f"port {a.port}, {a.background} background, Sun {a.sun_elevation_deg} vs {b.sun_elevation_deg} deg "
            f"(closer than {SUN_MARGIN_DEG} deg)"
        )
    return None


def check_disjoint(sets: dict[str, list[SequenceSpec]]) -> None:
    """ConfigError listing every clash between two different sets (at most 10 shown)."""
    names = list(sets)
    clashes = []
    for i, na in enumerate(names):
        for nb in names[i + 1 :]:
            for a in sets[na]:
                for b in sets[nb]:
                    why = _clash(a, b)
                    if why:
                        clashes.append(f"{na} {a.name} and {nb} {b.name}: {why}")
    if clashes:
        more = f"\n  ... and {len(clashes) - 10} more" if len(clashes) > 10 else ""
        raise ConfigError(
            f"the {', '.join(names)} sets overlap, so validation or test figures would not be honest:\n  "
            + "\n  ".join(clashes[:10])
            + more
        )
