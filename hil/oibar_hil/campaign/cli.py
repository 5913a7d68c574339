"""Command line of the dispersion campaigns (docs/campaign.md).

    python -m oibar_hil.campaign run [--config hil/campaigns/default.toml] [--missions N] [--nav cnn]
                                     [--workers K | --address HOST:PORT] [--executor serial]
                                     [--allow-code-change REASON]
    python -m oibar_hil.campaign report CAMPAIGN_DIR
    python -m oibar_hil.campaign pack CAMPAIGN_DIR --to DEST_DIR
    python -m oibar_hil.campaign replay CAMPAIGN_DIR INDEX
    python -m oibar_hil.campaign draws [--config FILE] [--first I] [--count N]

``run`` writes build/campaigns/<name>/ (``--out`` to change): a part per mission the moment it
finishes, then missions.parquet and report.md. Run it again with the same arguments to resume a
stopped campaign (only the missing missions fly); a larger ``--missions`` extends it. A campaign
flies one version of the code: a resume from a checkout whose fingerprint (fingerprint.py: the
host, firmware, proto, hil sources, the models for cnn, the simulated MCU binary) differs from
the one campaign.json recorded is refused (exit 3) unless ``--allow-code-change REASON``; so is
a mission a Ray worker flew with other code (its own checkout's fingerprint): its row is not
written and the run stops (exit 3), or with the reason the row is kept under the worker's code.

``pack`` writes DEST_DIR/campaign.json and DEST_DIR/missions.parquet (every finished row, zstd):
the form to commit (hil/campaigns/results/<name>/). A folder holding missions.parquet and fewer
parts (or none) resumes from the table: its rows count as finished, new parts go beside it, and
``report`` merges both.

Exit status:
  0  run: every planned mission is in the table; report, pack: written; replay: the mission
     reproduced its stored row (or had none); draws: printed
  1  run: some missions are not in the table (interrupted, Ray did not start, or a mission's
     worker was lost more than --max-retries times): run again to resume; replay: the mission
     differs from its stored row
  2  bad arguments: an invalid campaign file, no simulated MCU, a missing model, an unknown index,
     a folder that is not a campaign (no campaign.json)
  3  the folder holds another campaign, or was flown by other code (a changed fingerprint, or a
     Ray worker's that differs from the campaign's: that mission is not written, a resume flies
     it; no --allow-code-change), or another run is writing to it; its missions.parquet cannot
     be read, holds another campaign's rows (name, seed, model) or rows of code campaign.json
     does not record, or disagrees with a part of the same mission; pack: DEST_DIR holds another
     campaign or missions CAMPAIGN_DIR lacks
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import os
import sys
from pathlib import Path
from typing import Any

from oibar_hil.campaign.dispersion import NAVS, ConfigError, load_config
from oibar_hil.rig.runner import REPO_ROOT

DEFAULT_CONFIG = REPO_ROOT / "hil" / "campaigns" / "default.toml"
DEFAULT_ROOT = REPO_ROOT / "build" / "campaigns"
EXIT_OK, EXIT_INCOMPLETE, EXIT_USAGE, EXIT_FOLDER = 0, 1, 2, 3


def _positive(text: str) -> int:
    try:
        v = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"{text!r} is not a whole number") from None
    if v < 1:
        raise argparse.ArgumentTypeError(f"must be >= 1, got {v}")
    return v


def _non_negative(text: str) -> int:
    try:
        v = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"{text!r} is not a whole number") from None
    if v < 0:
        raise argparse.ArgumentTypeError(f"must be >= 0, got {v}")
    return v


def _reason(text: str) -> str:
    if not text.strip():
        raise argparse.ArgumentTypeError("give the reason the code change is acceptable")
    return text.strip()


def _parser() -> argparse.ArgumentParser:
    ap = argparse.ArgumentParser(
        prog="python -m oibar_hil.campaign",
        description="Monte Carlo dispersion campaigns on the HIL rig (issue 62)",
        epilog="Exit status: 0 done, 1 incomplete (resume) or not reproduced, 2 bad arguments, "
        "3 the folder holds another campaign, was flown by other code (this checkout's or a "
        "worker's), is in use, or its missions.parquet is unreadable or not this campaign's.",
    )
    sub = ap.add_subparsers(dest="cmd", required=True)
    run = sub.add_parser("run", help="run (or resume) a campaign")
    run.add_argument("--config", type=Path, default=DEFAULT_CONFIG, help="dispersion model (TOML)")
    run.add_argument("--name", default=None, help="campaign name (default: the file's [campaign] name)")
    run.add_argument(
        "--out", type=Path, default=None, help="campaign folder (default build/campaigns/<name>)"
    )
    run.add_argument("--missions", type=_positive, default=None, help="missions 0..N-1 (default: the file's)")
    run.add_argument("--seed", type=_non_negative, default=None, help="campaign seed (default: the file's)")
    run.add_argument("--nav", choices=NAVS, default=None, help="navigation (default: the file's)")
    run.add_argument(
        "--model", type=Path, default=None, help="ONNX model for --nav cnn (default the shipped one)"
    )
    run.add_argument("--mcu", type=Path, default=None, help="simulated MCU (default build/fw-host's)")
    run.add_argument(
        "--executor",
        choices=("ray", "serial"),
        default="ray",
        help="ray: Ray tasks, local processes or --address (default); serial: every mission in this process",
    )
    run.add_argument(
        "--workers", type=_positive, default=None, help="local Ray worker processes (default: cores)"
    )
    run.add_argument(
        "--address", default=None, help="an existing Ray cluster (ray start --head ...): HOST:PORT or auto"
    )
    run.add_argument(
        "--max-retries",
        type=_non_negative,
        default=3,
        help="reruns of a mission whose worker died (default 3)",
    )
    run.add_argument(
        "--nice",
        type=int,
        choices=range(0, 20),
        metavar="0..19",
        default=0,
        help="run the missions at this niceness (a shared machine); the driver and Ray stay at normal priority",
    )
    run.add_argument(
        "--allow-code-change",
        metavar="REASON",
        type=_reason,
        default=None,
        help="resume a campaign flown by other code anyway, and keep missions a worker flies with "
        "other code (recorded with REASON in campaign.json and the report)",
    )
    run.add_argument("--no-progress", action="store_true")
    run.add_argument("--no-report", action="store_true", help="only the parts; `report` later")
    rep = sub.add_parser("report", help="missions.parquet and report.md of a campaign folder")
    rep.add_argument("folder", type=Path)
    rep.add_argument("--no-figures", action="store_true")
    pck = sub.add_parser(
        "pack",
        help="campaign.json + missions.parquet of a campaign folder, to commit (a later session resumes from it)",
    )
    pck.add_argument("folder", type=Path)
    pck.add_argument(
        "--to", type=Path, required=True, metavar="DEST_DIR", help="e.g. hil/campaigns/results/<name>"
    )
    rpl = sub.add_parser("replay", help="fly one mission of a campaign again, with the rig's full report")
    rpl.add_argument("folder", type=Path)
    rpl.add_argument("index", type=_non_negative)
    rpl.add_argument("--model", type=Path, default=None)
    rpl.add_argument("--mcu", type=Path, default=None)
    rpl.add_argument(
        "--out", type=Path, default=None, help="report folder (default CAMPAIGN_DIR/replay/NNNNNN)"
    )
    drw = sub.add_parser("draws", help="print missions' drawn inputs and faults (JSON lines)")
    drw.add_argument("--config", type=Path, default=DEFAULT_CONFIG)
    drw.add_argument("--seed", type=_non_negative, default=None)
    drw.add_argument("--first", type=_non_negative, default=0)
    drw.add_argument("--count", type=_positive, default=5)
    return ap


def _err(text: str) -> None:
    print(f"error: {text}", file=sys.stderr)


def _check_paths(mcu: Path | None, model: Path | None, nav: str) -> str | None:
    from oibar_hil.rig.fw_params import default_mcu_path

    mcu_path = mcu or default_mcu_path()
    if not Path(mcu_path).exists():
        return f"no simulated MCU at {mcu_path} (run `make firmware-host`)"
    if nav == "cnn" and model is not None and not model.exists():
        return f"no model file {model}"
    return None


def summarise(folder: Path, figures: bool = True) -> tuple[Path, list[dict[str, Any]]]:
    """missions.parquet + report.md of a campaign folder; -> (report path, rows)."""
    from oibar_hil.campaign.report import write_report
    from oibar_hil.campaign.store import load_config as load_folder_config
    from oibar_hil.campaign.store import read_rows, write_table

    cfg = load_folder_config(folder)
    rows = read_rows(folder)
    write_table(folder, rows)
    return write_report(folder, rows, cfg, figures=figures), rows


def _print_rates(rows: list[dict[str, Any]]) -> None:
    from oibar_hil.campaign.stats import rate

    clean = [r for r in rows if not r["fault"]]
    faulted = [r for r in rows if r["fault"]]
    print(f"  all missions:      {rate(sum(r['success'] for r in rows), len(rows)).text()}")
    if clean:
        print(f"  fault-free:        {rate(sum(r['success'] for r in clean), len(clean)).text()}")
    if faulted:
        print(f"  with a fault:      {rate(sum(r['success'] for r in faulted), len(faulted)).text()}")


def cmd_run(args: argparse.Namespace) -> int:
    from oibar_hil.campaign.execute import NICE_ENV, RayStartError, run_missions
    from oibar_hil.campaign.fingerprint import describe
    from oibar_hil.campaign.store import CampaignFolderError, CodeChangedError, locked, open_campaign

    try:
        cfg = load_config(args.config)
    except ConfigError as exc:
        _err(str(exc))
        return EXIT_USAGE
    over: dict[str, Any] = {}
    for key in ("name", "missions", "seed", "nav"):
        if getattr(args, key) is not None:
            over[key] = getattr(args, key)
    if "name" in over and (not over["name"] or "/" in over["name"] or over["name"].startswith(".")):
        _err(f"--name {over['name']!r}: a folder name without slashes")
        return EXIT_USAGE
    cfg = dataclasses.replace(cfg, **over)
    problem = _check_paths(args.mcu, args.model, cfg.nav)
    if problem:
        _err(problem)
        return EXIT_USAGE
    folder = args.out or (DEFAULT_ROOT / cfg.name)
    mcu = str(args.mcu.resolve()) if args.mcu else None
    model = str(args.model.resolve()) if args.model else None
    if args.executor == "ray" and args.address is None and args.workers is None:
        args.workers = os.cpu_count() or 1
    if args.nice:
        os.environ[NICE_ENV] = str(args.nice)
    try:
        with locked(folder):
            code = open_campaign(
                folder, cfg, mcu_path=mcu, model_path=model, allow_code_change=args.allow_code_change
            )
            if code.status == "allowed":
                print(
                    f"code changed ({', '.join(code.changed)}): {describe(code.previous)} -> "
                    f"{describe(code.fingerprint)}, resumed anyway: {args.allow_code_change!r} "
                    "(recorded in campaign.json)",
                    file=sys.stderr,
                )
            elif code.status == "adopted":
                print(
                    f"{folder / 'campaign.json'} had no code fingerprint (made before them): "
                    f"recorded this checkout's, {describe(code.fingerprint)}; the rows already there "
                    "carry no code_sha",
                    file=sys.stderr,
                )
            summary = run_missions(
                cfg,
                folder,
                executor=args.executor,
                workers=args.workers,
                address=args.address,
                max_retries=args.max_retries,
                mcu_path=mcu,
                model_path=model,
                progress=not args.no_progress,
                code=code.fingerprint,
                allow_code_change=args.allow_code_change,
            )
            report_path, rows = (None, None) if args.no_report else summarise(folder)
    except CodeChangedError as exc:
        _err(f"{exc} (exit {EXIT_FOLDER})")
        return EXIT_FOLDER
    except CampaignFolderError as exc:
        _err(str(exc))
        return EXIT_FOLDER
    except RayStartError as exc:
        _err(f"{exc}; the missions already flown are kept")
        return EXIT_INCOMPLETE
    print(
        f"campaign {cfg.name} ({cfg.nav}, seed {cfg.seed}, code {code.short}): "
        f"{summary.already_done} missions already done, "
        f"{summary.finished} flown now in {summary.wall_s:.0f} s on {summary.workers} worker(s)"
    )
    if rows:
        _print_rates([r for r in rows if r["index"] < cfg.missions])
    if report_path:
        print(f"  table: {folder / 'missions.parquet'}\n  report: {report_path}")
    if summary.lost:
        for i, why in summary.lost:
            print(f"  mission {i} not run: {why}", file=sys.stderr)
    if not summary.complete:
        print(
            f"incomplete: {'interrupted; ' if summary.interrupted else ''}run the same command again to resume",
            file=sys.stderr,
        )
        return EXIT_INCOMPLETE
    return EXIT_OK


def cmd_report(args: argparse.Namespace) -> int:
    from oibar_hil.campaign.store import CONFIG_FILE, CampaignFolderError

    if not (args.folder / CONFIG_FILE).exists():
        _err(f"{args.folder} is not a campaign folder (no {CONFIG_FILE})")
        return EXIT_USAGE
    try:
        path, rows = summarise(args.folder, figures=not args.no_figures)
    except CampaignFolderError as exc:
        _err(str(exc))
        return EXIT_FOLDER
    print(f"{len(rows)} missions in {args.folder / 'missions.parquet'}")
    if rows:
        _print_rates(rows)
    print(f"report: {path}")
    return EXIT_OK


def cmd_pack(args: argparse.Namespace) -> int:
    from oibar_hil.campaign.store import CONFIG_FILE, CampaignFolderError, index_ranges, load_config, pack

    if not (args.folder / CONFIG_FILE).exists():
        _err(f"{args.folder} is not a campaign folder (no {CONFIG_FILE})")
        return EXIT_USAGE
    try:
        cfg = load_config(args.folder)
        path, rows = pack(args.folder, args.to)
    except CampaignFolderError as exc:
        _err(str(exc))
        return EXIT_FOLDER
    done = {int(r["index"]) for r in rows}
    missing = [i for i in range(cfg.missions) if i not in done]
    print(
        f"packed {len(rows)} missions of campaign {cfg.name} into {path} ({path.stat().st_size} bytes, "
        f"zstd) and {args.to / CONFIG_FILE}"
    )
    if missing:
        print(f"  not flown yet: {len(missing)} of {cfg.missions} ({index_ranges(missing)[:200]})")
    print(f"  resume elsewhere: copy {args.to} to build/campaigns/{cfg.name} and run the same `run` command")
    return EXIT_OK


def cmd_replay(args: argparse.Namespace) -> int:
    from oibar_hil.campaign.fingerprint import changed_groups, code_fingerprint, describe
    from oibar_hil.campaign.mission import VOLATILE_COLUMNS, run_mission
    from oibar_hil.campaign.store import CampaignFolderError, code_record, current_code, stored_row
    from oibar_hil.campaign.store import load_config as load_folder_config
    from oibar_hil.rig.report import write_report

    try:
        cfg = load_folder_config(args.folder)
    except CampaignFolderError as exc:
        _err(str(exc))
        return EXIT_USAGE
    if args.index >= cfg.missions:
        _err(f"mission {args.index} is not in campaign {cfg.name} (missions 0..{cfg.missions - 1})")
        return EXIT_USAGE
    problem = _check_paths(args.mcu, args.model, cfg.nav)
    if problem:
        _err(problem)
        return EXIT_USAGE
    out = args.out or (args.folder / "replay" / f"{args.index:06d}")
    run = run_mission(
        cfg,
        args.index,
        mcu_path=str(args.mcu) if args.mcu else None,
        model_path=str(args.model) if args.model else None,
        out_dir=out,
    )
    row = run.row
    now = code_fingerprint(cfg.nav, mcu_path=args.mcu, model_path=args.model)
    row["code_sha"] = now["short"]
    if run.result is not None:
        report = write_report(run.result, out)
        print(f"report: {report}")
    print(
        f"mission {args.index} of {cfg.name}: {row['outcome']}, {'success' if row['success'] else 'FAILED'}"
        + (f" ({row['failed_checks'] or row['error']})" if not row["success"] else "")
        + (f"; fault {row['fault']}@{row['fault_phase']}" if row["fault"] else "")
    )
    try:
        stored = stored_row(args.folder, args.index)
    except CampaignFolderError as exc:
        _err(str(exc))
        return EXIT_FOLDER
    if stored is None:
        print("no stored row for this mission (not flown yet): nothing to compare")
        return EXIT_OK
    if stored.get("code_sha") and stored["code_sha"] != now["short"]:
        flew = current_code(code_record(args.folder)) or {}
        changed = changed_groups(flew, now) if flew.get("short") == stored["code_sha"] else []
        print(
            f"note: flown by code {stored['code_sha']}, replayed by {describe(now)}"
            + (f" ({', '.join(changed)} changed)" if changed else "")
        )
    skip = (*VOLATILE_COLUMNS, "code_sha")
    diff = [k for k in row if k not in skip and k in stored and stored[k] != row[k]]
    if diff:
        for k in diff:
            print(f"  differs: {k}: stored {stored[k]!r}, now {row[k]!r}")
        return EXIT_INCOMPLETE
    print("reproduced: every column but the wall times matches the stored row")
    return EXIT_OK


def cmd_draws(args: argparse.Namespace) -> int:
    from oibar_hil.campaign.dispersion import draw_mission

    try:
        cfg = load_config(args.config)
    except ConfigError as exc:
        _err(str(exc))
        return EXIT_USAGE
    if args.seed is not None:
        cfg = dataclasses.replace(cfg, seed=args.seed)
    for i in range(args.first, args.first + args.count):
        d = draw_mission(cfg, i)
        dispersed = {k: float(f"{v:.6g}") for k, v in d.values.items() if k in d.dispersed}
        print(
            json.dumps(
                {"index": i, "fault": d.fault, "phase": d.fault_phase, "rig_seed": d.rig_seed, **dispersed}
            )
        )
    return EXIT_OK


def main(argv: list[str] | None = None) -> int:
    args = _parser().parse_args(argv)
    commands = {
        "run": cmd_run,
        "report": cmd_report,
        "pack": cmd_pack,
        "replay": cmd_replay,
        "draws": cmd_draws,
    }
    return commands[args.cmd](args)


if __name__ == "__main__":
    sys.exit(main())
