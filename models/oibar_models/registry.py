"""The model registry (models/registry.toml): which models ship, from which recipe and commit,
with which files (sha256), data sets and checkpoints, and which metrics; and the two things made
from it: the reproduction rule and the model card's tables.

The reproduction rule is not the ship rule. The ship rule (oibar_models.judge) asks a candidate
to beat the shipped model; this one asks a rebuild of a registered model, from its recipe, to land
where the registry says it did: validation position and attitude within the registry's stated
tolerance, and compliance no lower.

    python -m oibar_models.registry check MODEL METRICS.json [--registry models/registry.toml]
    python -m oibar_models.registry card [--check] [--card docs/model_card.md]
    python -m oibar_models.registry verify     # the shipped files' and every entry's records' sha256

An entry's records (its [models.records] table) are the files it needs kept, beside the registry
under models/registry/NAME-VERSION/: the tables its export read, the evaluations its metrics come
from, its ship verdict and the ship rule's bases. The rest of the history is in MLflow
(oibar_models.history).
"""

from __future__ import annotations

import argparse
import hashlib
import json
import math
import sys
import tomllib
from pathlib import Path
from typing import Any

from .config import REPO_ROOT

REGISTRY = REPO_ROOT / "models" / "registry.toml"
CARD = REPO_ROOT / "docs" / "model_card.md"
BEGIN = "<!-- BEGIN registry tables (python -m oibar_models.registry card; do not edit by hand) -->"
END = "<!-- END registry tables -->"
# the metrics the rule compares, with the direction that is better
POSITION, ATTITUDE = "dt_mean_pct", "dq_mean_deg"
COMPLIANCE = ("compliance_pos_pct", "compliance_att_pct")
CARD_COLUMNS = (
    ("frames", "frames", "{:d}"),
    ("dt_mean_pct", "position mean", "{:.3f}"),
    ("dt_median_pct", "position median", "{:.3f}"),
    ("dq_mean_deg", "attitude mean", "{:.3f}"),
    ("dq_median_deg", "attitude median", "{:.3f}"),
)


class RegistryError(ValueError):
    """The registry file is missing, not TOML, or an entry lacks what the rule or the card needs."""


def load_registry(path: Path = REGISTRY) -> dict:
    try:
        doc = tomllib.loads(Path(path).read_text())
    except OSError as exc:
        raise RegistryError(f"{path}: cannot read the registry ({exc})") from exc
    except tomllib.TOMLDecodeError as exc:
        raise RegistryError(f"{path}: not valid TOML ({exc})") from exc
    rule = doc.get("reproduction")
    if not isinstance(rule, dict) or not {"position_pct", "attitude_deg"} <= set(rule):
        raise RegistryError(f"{path}: [reproduction] needs position_pct and attitude_deg (the tolerances)")
    models = doc.get("models")
    if not isinstance(models, list) or not models:
        raise RegistryError(f"{path}: no [[models]] entries")
    for i, m in enumerate(models):
        for key in ("name", "version", "status", "files", "metrics"):
            if key not in m:
                raise RegistryError(f"{path}: models[{i}] ({m.get('name', '?')}): {key} is required")
        if m["status"] not in ("shipped", "retired"):
            raise RegistryError(f"{path}: {m['name']} {m['version']}: status is shipped or retired")
        if not isinstance(m.get("records", {}), dict):
            raise RegistryError(f"{path}: {m['name']} {m['version']}: records is a table of path = sha256")
    return doc


def find(doc: dict, name: str, version: str | None = None) -> dict:
    """The entry `name` (its shipped one unless `version` says which)."""
    hits = [
        m
        for m in doc["models"]
        if m["name"] == name and (m["version"] == version if version else m["status"] == "shipped")
    ]
    if len(hits) != 1:
        raise RegistryError(
            f"no single registry entry for {name} {version or '(shipped)'}: {len(hits)} found"
        )
    return hits[0]


def reproduces(reference: dict, rebuild: dict, tolerance: dict) -> list[str]:
    """The reproduction rule: [] when the rebuild's validation metrics lie within `tolerance` of the
    reference's (position_pct and attitude_deg, either way) and neither compliance is lower; else
    one line per clause that fails. A metric missing or not finite fails its clause."""
    fails = []
    for key, tol in ((POSITION, tolerance["position_pct"]), (ATTITUDE, tolerance["attitude_deg"])):
        ref: Any = reference.get(key)
        got: Any = rebuild.get(key)
        if not _finite(ref) or not _finite(got):
            fails.append(f"{key}: registry {ref}, rebuild {got}: not both finite numbers")
        elif abs(float(got) - float(ref)) > tol + 1e-12:
            d = float(got) - float(ref)
            fails.append(
                f"{key}: rebuild {got:.4f} is {d:+.4f} from the registry's {ref:.4f} (allowed +-{tol})"
            )
    for key in COMPLIANCE:
        ref, got = reference.get(key), rebuild.get(key)
        if not _finite(ref) or not _finite(got):
            fails.append(f"{key}: registry {ref}, rebuild {got}: not both finite numbers")
        elif float(got) < float(ref) - 1e-9:
            fails.append(f"{key}: rebuild {got:.2f} % is lower than the registry's {ref:.2f} %")
    return fails


def _finite(x: Any) -> bool:
    return isinstance(x, (int, float)) and not isinstance(x, bool) and math.isfinite(x)


# ----------------------------------------------------------------------------- the card
def _fmt(v: Any, f: str) -> str:
    return f.format(v) if _finite(v) else ""


def card_rows(rows: list[tuple[str, dict]]) -> str:
    """A markdown accuracy table: one row per (label, metrics)."""
    head = "| (position: % of range; attitude: deg) | " + " | ".join(c[1] for c in CARD_COLUMNS)
    out = [head + " | compliance (5 %, 5 deg) |", "| --- |" + " ---: |" * len(CARD_COLUMNS) + " --- |"]
    for label, m in rows:
        cells = [_fmt(m.get(k), f) for k, _, f in CARD_COLUMNS]
        comp = (
            f"{m['compliance_pos_pct']:.2f} / {m['compliance_att_pct']:.2f} %"
            if all(_finite(m.get(k)) for k in COMPLIANCE)
            else ""
        )
        out.append(f"| {label} | " + " | ".join(cells) + f" | {comp} |")
    return "\n".join(out) + "\n"


def card_section(doc: dict) -> str:
    """What the card holds between its markers: the registered models, then each metrics set."""
    lines = [
        "| model | version | status | files (sha256, first 12) | built from | recipe |",
        "| --- | --- | --- | --- | --- | --- |",
    ]
    for m in doc["models"]:
        files = ", ".join(f"`{Path(p).name}` {sha[:12]}" for p, sha in m["files"].items())
        recipe = m.get("recipe", "") or "none"
        if m.get("recipe_status"):
            recipe += f" ({m['recipe_status']})"
        lines.append(
            f"| {m['name']} | {m['version']} | {m['status']} | {files} | {m.get('commit', '')[:7]} | {recipe} |"
        )
    rows = []
    for m in doc["models"]:
        for set_name, metrics in m["metrics"].items():
            label = metrics.get("label", set_name)
            rows.append((f"{label}, {m['name']} {m['version']}", metrics))
    tol = doc["reproduction"]
    return (
        "\n".join(lines)
        + "\n\n"
        + card_rows(rows)
        + (
            f"\nReproduction rule (a rebuild from the recipe, not a candidate): validation position within "
            f"+-{tol['position_pct']} % and attitude within +-{tol['attitude_deg']} deg of the registry's, "
            "compliance no lower (`python -m oibar_models.registry check`).\n"
        )
    )


def render_card(card_text: str, doc: dict) -> str:
    if (
        card_text.count(BEGIN) != 1
        or card_text.count(END) != 1
        or card_text.index(BEGIN) > card_text.index(END)
    ):
        raise RegistryError("the model card needs one BEGIN and one END registry marker, in that order")
    head, rest = card_text.split(BEGIN)
    _, tail = rest.split(END)
    return head + BEGIN + "\n" + card_section(doc) + END + tail


# ----------------------------------------------------------------------------- writing an entry
def _toml_value(v: Any) -> str:
    if isinstance(v, bool):
        return "true" if v else "false"
    if isinstance(v, (int, float)):
        return repr(v) if _finite(v) else "nan"
    if isinstance(v, str):
        return json.dumps(v)
    if isinstance(v, list):
        return "[" + ", ".join(_toml_value(x) for x in v) + "]"
    raise TypeError(f"no TOML for {type(v).__name__}")


def entry_toml(entry: dict) -> str:
    """A registry entry ([[models]] with its tables) as TOML text, to paste into the registry
    once a rebuild has passed the rule (a build's card stage writes it)."""
    scalars = {k: v for k, v in entry.items() if not isinstance(v, dict)}
    out = ["[[models]]", *(f"{k} = {_toml_value(v)}" for k, v in scalars.items())]
    for k, v in entry.items():
        if isinstance(v, dict):
            table = k if k in ("files", "datasets", "checkpoints", "records") else f"metrics.{k}"
            out.append(f"[models.{table}]")
            out.extend(f"{json.dumps(str(kk))} = {_toml_value(vv)}" for kk, vv in v.items())
    return "\n".join(out) + "\n"


def verify(doc: dict, root: Path = REPO_ROOT) -> list[str]:
    """The shipped entries' files, and every entry's records (committed, whatever its status),
    against their recorded sha256: one line per mismatch."""
    bad = []
    for m in doc["models"]:
        files = dict(m["files"]) if m["status"] == "shipped" else {}
        files.update(m.get("records", {}))
        for rel, sha in files.items():
            p = root / rel
            if not p.is_file():
                bad.append(f"{rel}: missing")
            elif hashlib.sha256(p.read_bytes()).hexdigest() != sha:
                bad.append(f"{rel}: sha256 differs from the registry's ({m['name']} {m['version']})")
    return bad


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="python -m oibar_models.registry", description=__doc__.split("\n\n")[0])
    ap.add_argument("--registry", type=Path, default=REGISTRY)
    sub = ap.add_subparsers(dest="cmd", required=True)
    c = sub.add_parser(
        "check", help="the reproduction rule: a rebuild's validation metrics against the registry"
    )
    c.add_argument("model", help="a registry name (its shipped version unless --version)")
    c.add_argument("metrics", type=Path, help="the rebuild's metrics.json (a build's evaluate stage)")
    c.add_argument("--version", default=None)
    c.add_argument(
        "--set", default="validation", help="which of the entry's metrics sets (default validation)"
    )
    k = sub.add_parser("card", help="write the card's registry tables (--check: fail if they differ)")
    k.add_argument("--card", type=Path, default=CARD)
    k.add_argument("--check", action="store_true")
    sub.add_parser("verify", help="the shipped files and the records against their sha256")
    a = ap.parse_args(argv)
    try:
        doc = load_registry(a.registry)
        if a.cmd == "check":
            ref = find(doc, a.model, a.version)
            if a.set not in ref["metrics"]:
                raise RegistryError(f"{ref['name']} {ref['version']} has no {a.set!r} metrics")
            got = json.loads(a.metrics.read_text())
            fails = reproduces(ref["metrics"][a.set], got, doc["reproduction"])
            for f in fails:
                print(f"fails: {f}")
            print(f"{ref['name']} {ref['version']}: {'not ' if fails else ''}reproduced ({a.metrics})")
            return 1 if fails else 0
        if a.cmd == "card":
            text = a.card.read_text()
            new = render_card(text, doc)
            if a.check:
                if new != text:
                    print(
                        f"{a.card}: the registry tables differ from {a.registry}: run "
                        "`python -m oibar_models.registry card`",
                        file=sys.stderr,
                    )
                    return 1
                return 0
            a.card.write_text(new)
            print(f"{a.card}: registry tables written")
            return 0
        bad = verify(doc)
        for line in bad:
            print(line)
        return 1 if bad else 0
    except (RegistryError, OSError, json.JSONDecodeError) as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2


if __name__ == "__main__":
    raise SystemExit(main())
