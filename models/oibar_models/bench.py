"""Backbone benchmark (cost side): parameters, ONNX single-stream latency on this machine and
PyTorch training throughput, per config. Weights are random: latency and throughput do not
depend on them; accuracy comes from evaluate.py on trained models.

CLI: python -m oibar_models.bench models/configs/*.yaml [--threads 2] [--seconds 5] [--train-steps 3]
"""

from __future__ import annotations

import argparse
import json
import os
import tempfile
import time
from pathlib import Path

import torch

from .config import load_config
from .export import export_onnx
from .infer import benchmark
from .loss import UncertaintyPoseLoss
from .nets import build_model, count_parameters


def bench_config(path: str, threads: int, seconds: float, train_steps: int, batch: int) -> dict:
    cfg = load_config(path)
    net = build_model(cfg.model)
    w, h = cfg.model.input_width_px, cfg.model.input_height_px
    ck = {
        "config": cfg.to_dict(),
        "labels": {"mean_T_cam_target": [0, 0, 0], "mean_q_cam_target": [1, 0, 0, 0]},
    }
    with tempfile.TemporaryDirectory() as tmp:
        onnx_path = export_onnx(net, ck, Path(tmp) / "m.onnx")
        size_mib = onnx_path.stat().st_size / 2**20
        lat = benchmark(onnx_path, threads=threads, seconds=seconds, with_preprocess=False)
    row = {
        "config": Path(path).stem,
        "backbone": cfg.model.backbone,
        "input": f"{w}x{h}",
        "params_M": count_parameters(net) / 1e6,
        "onnx_MiB": size_mib,
        "ort_ms": lat["mean_ms"],
        "ort_per_s": lat["inferences_per_s"],
        "threads": threads,
    }
    if train_steps > 0:
        torch.set_num_threads(threads)
        net.train()
        crit = UncertaintyPoseLoss()
        opt = torch.optim.Adam(list(net.parameters()) + list(crit.parameters()), 1e-4)
        x, T, r6 = torch.rand(batch, 3, h, w), torch.rand(batch, 3), torch.rand(batch, 6)
        times = []
        for i in range(train_steps + 1):
            t0 = time.perf_counter()
            loss = crit(*net(x), T, r6)["loss"]
            opt.zero_grad()
            loss.backward()
            opt.step()
            if i:  # the first step pays one-off allocations
                times.append(time.perf_counter() - t0)
        row["train_img_per_s"] = batch * len(times) / sum(times)
        row["train_batch"] = batch
    return row


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="python -m oibar_models.bench", description=__doc__.split("\n\n")[0])
    ap.add_argument("configs", nargs="+")
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--seconds", type=float, default=5.0)
    ap.add_argument("--train-steps", type=int, default=3)
    ap.add_argument("--batch", type=int, default=16)
    ap.add_argument("--json", help="also write the rows here")
    a = ap.parse_args(argv)
    rows = []
    print(f"load average before: {os.getloadavg()[0]:.2f}")
    print("| config | backbone | input | params (M) | ONNX (MiB) | ORT ms (batch 1) | ORT /s | train img/s |")
    print("| --- | --- | --- | ---: | ---: | ---: | ---: | ---: |")
    for c in a.configs:
        r = bench_config(c, a.threads, a.seconds, a.train_steps, a.batch)
        rows.append(r)
        print(
            f"| {r['config']} | {r['backbone']} | {r['input']} | {r['params_M']:.2f} | {r['onnx_MiB']:.1f} | "
            f"{r['ort_ms']:.1f} | {r['ort_per_s']:.1f} | {r.get('train_img_per_s', float('nan')):.1f} |",
            flush=True,
        )
    print(f"load average after: {os.getloadavg()[0]:.2f}")
    if a.json:
        Path(a.json).write_text(json.dumps(rows, indent=1) + "\n")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
