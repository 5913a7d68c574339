"""The model registry (models/registry.toml): the shipped files are the registered ones, the card's
tables are the registry's, and the reproduction rule passes a rebuild within its tolerance and
fails one outside it (issue 61, item 2)."""

from __future__ import annotations

import json
import math
import tomllib

import pytest

from oibar_models.registry import (
    BEGIN,
    CARD,
    END,
    REGISTRY,
    RegistryError,
    entry_toml,
    find,
    load_registry,
    main,
    render_card,
    reproduces,
    verify,
)


@pytest.fixture(scope="module")
def doc() -> dict:
    return load_registry()


def test_the_shipped_files_are_the_registered_ones(doc):
    assert verify(doc) == []
    shipped = {p for m in doc["models"] if m["status"] == "shipped" for p in m["files"]}
    assert shipped == {"models/oibarnet.onnx", "models/oibarnet_finder.onnx", "models/oibarnet_lite.onnx"}


def test_the_shipped_keypoint_model_is_its_recipes_and_names_its_finder(doc):
    """0.35.15 is built by its recipe, whose retag stage names the finder the registry ships."""
    from oibar_models.recipe import load_recipe

    m = find(doc, "oibarnet")
    assert m["version"] == "0.35.15" and m["recipe"] == "models/recipes/oibarnet_kp_ft_cropgain_used5.toml"
    recipe = load_recipe(REGISTRY.parent.parent / m["recipe"])
    assert recipe.model_version == m["version"] and recipe.stage("retag").opts["finder"] == "finder"
    assert all(math.isfinite(m["metrics"]["validation"][k]) for k in ("dt_mean_pct", "dq_mean_deg"))


def test_the_retired_model_the_recipes_start_from_is_kept_with_its_files(doc):
    """0.34.0 is retired, and its files lie beside its records: the 0.35.x recipes fine-tune it."""
    old = find(doc, "oibarnet", "0.34.0")
    assert old["status"] == "retired" and len(old["commit"]) == 40 and "not rebuilt" in old["recipe_status"]
    assert verify({"models": [dict(old, status="shipped")]}) == []


def test_the_card_tables_are_the_registrys(doc):
    text = CARD.read_text()
    assert render_card(text, doc) == text, "run `python -m oibar_models.registry card`"
    block = text.split(BEGIN)[1].split(END)[0]
    assert "0.4836" not in block and "0.484" in block  # the figures, rounded as the card shows them
    assert main(["card", "--check"]) == 0


def test_a_card_out_of_step_with_the_registry_is_caught(doc, tmp_path):
    card = tmp_path / "card.md"
    card.write_text(CARD.read_text().replace("| 0.484 |", "| 0.480 |", 1))
    assert main(["card", "--check", "--card", str(card)]) == 1
    assert main(["card", "--card", str(card)]) == 0 and card.read_text() == CARD.read_text()
    card.write_text("no markers here\n")
    with pytest.raises(RegistryError, match="marker"):
        render_card(card.read_text(), doc)


def test_the_reproduction_rule(doc):
    ref = find(doc, "oibarnet")["metrics"]["validation"]
    tol = doc["reproduction"]
    assert tol["position_pct"] == 0.02 and tol["attitude_deg"] == 0.02
    assert reproduces(ref, dict(ref), tol) == []
    within = dict(ref, dt_mean_pct=ref["dt_mean_pct"] + 0.019, dq_mean_deg=ref["dq_mean_deg"] - 0.019)
    assert reproduces(ref, within, tol) == []
    # either way counts: better by more than the tolerance is not a reproduction either
    for key, delta in (("dt_mean_pct", 0.021), ("dt_mean_pct", -0.021), ("dq_mean_deg", 0.03)):
        fails = reproduces(ref, dict(ref, **{key: ref[key] + delta}), tol)
        assert len(fails) == 1 and fails[0].startswith(key)
    lower = dict(ref, compliance_att_pct=ref["compliance_att_pct"] - 0.01)
    assert [f.split(":")[0] for f in reproduces(ref, lower, tol)] == ["compliance_att_pct"]
    assert reproduces(ref, dict(ref, compliance_pos_pct=100.0), tol) == []  # higher is fine
    assert len(reproduces(ref, dict(ref, dq_mean_deg=float("nan")), tol)) == 1
    missing = {k: v for k, v in ref.items() if k != "dt_mean_pct"}
    assert len(reproduces(ref, missing, tol)) == 1


def test_the_check_command(doc, tmp_path, capsys):
    ref = find(doc, "oibarnet")["metrics"]["validation"]
    good, bad = tmp_path / "good.json", tmp_path / "bad.json"
    good.write_text(json.dumps(dict(ref, dq_mean_deg=ref["dq_mean_deg"] + 0.01)))
    bad.write_text(json.dumps(dict(ref, dq_mean_deg=ref["dq_mean_deg"] + 0.05)))
    assert main(["check", "oibarnet", str(good)]) == 0
    assert main(["check", "oibarnet", str(bad)]) == 1
    assert "dq_mean_deg" in capsys.readouterr().out
    assert main(["check", "oibarnet", str(good), "--version", "9.9.9"]) == 2
    assert main(["check", "oibarnet_lite", str(good)]) == 2  # no validation metrics registered


def test_a_build_entry_is_registry_toml(doc):
    entry = {
        "name": "oibarnet_kp",
        "version": "0.34.1",
        "recipe": "models/recipes/oibarnet_kp.toml",
        "files": {"export/oibarnet.onnx": "ab" * 32},
        "datasets": {"val": "cd" * 32},
        "checkpoints": {},
        "records": {"models/registry/oibarnet_kp-0.34.1/eval.json": "ef" * 32},
        "validation": {"dt_mean_pct": 0.3, "dq_mean_deg": 0.5, "frames": 10},
    }
    parsed = tomllib.loads(entry_toml(entry))["models"][0]
    assert parsed["files"] == entry["files"] and parsed["metrics"]["validation"] == entry["validation"]
    assert parsed["records"] == entry["records"]


def test_the_records_lie_beside_the_registry_and_the_judge_reads_them(doc, tmp_path):
    """Issue 61 item 3: what a shipped model needs is committed beside the registry, pinned by
    sha256 (verify checks them), every figure's source among them; nothing is read from docs/."""
    from oibar_models.config import REPO_ROOT
    from oibar_models.judge import BASE_LOOP, BASE_PROBE

    m = find(doc, "oibarnet")
    records = m["records"]
    assert records and all(p.startswith(f"models/registry/oibarnet-{m['version']}/") for p in records)
    for base in (BASE_PROBE, BASE_LOOP):
        assert str(base.relative_to(REPO_ROOT)) in records
    for entry in doc["models"]:
        for metrics in entry["metrics"].values():
            src = metrics.get("source", "")
            assert src and any(src in e.get("records", {}) for e in doc["models"]), src
    text = REGISTRY.read_text()
    assert "docs/data" not in text
    # a changed record is caught
    changed = tmp_path / "r.toml"
    first = next(iter(records))
    changed.write_text(text.replace(records[first], "0" * 64))
    assert verify(load_registry(changed)) == [
        f"{first}: sha256 differs from the registry's (oibarnet {m['version']})"
    ]


def test_a_malformed_registry_is_refused(tmp_path):
    bad = tmp_path / "r.toml"
    bad.write_text(REGISTRY.read_text().replace("position_pct = 0.02\n", ""))
    with pytest.raises(RegistryError, match="position_pct"):
        load_registry(bad)
    bad.write_text(REGISTRY.read_text().replace('status = "retired"', 'status = "maybe"'))
    with pytest.raises(RegistryError, match="shipped or retired"):
        load_registry(bad)
