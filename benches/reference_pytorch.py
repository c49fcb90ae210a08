#!/usr/bin/env python3
"""Time the reference DUSty v2 generator (PyTorch, github.com/kazuto1011/dusty-gan-v2) on the
same operations as `benches/generator_ops.rs`, and print one JSON line.

The reference code is NOT part of this repository: pass a checkout of it with
`--reference DIR` (e.g. `git archive` of the repository into /work/dusty-gan-v2). The generator
is built from the reference's own `configs/gans/dusty_v2.yaml` (the paper's 64x512 KITTI model,
4.37 M parameters) and run on the CPU, in eval mode (no subgrid augmentation; the reference's
inversion demo also runs `G.eval()`), from w (mapping excluded), with the reference's KITTI
angle table resampled to 64x512.

Operations (wall seconds per call after one warm-up call; `<op>_cpu`: process CPU seconds of
the same calls):
  fwd_b1, fwd_b8        forward under torch.no_grad()
  fwdbwd_b1, fwdbwd_b8  forward + backward of sum(image) + sum(raydrop_logit) to w and all weights
  inv_w_b1              forward, L1 to a fixed target, backward to w only, Adam step on w
  pti_b1                same loss, backward to w and all weights, Adam step on all of them

    python3 benches/reference_pytorch.py --reference /work/dusty-gan-v2 [--reps 3] [--threads 2]
"""

import argparse
import json
import os
import sys
import time
import types

ALL_OPS = ["fwd_b1", "fwd_b8", "fwdbwd_b1", "fwdbwd_b8", "inv_w_b1", "pti_b1"]


def parse_args():
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--reference", required=True, help="checkout of kazuto1011/dusty-gan-v2")
    p.add_argument("--reps", type=int, default=3)
    p.add_argument("--threads", type=int, default=2)
    p.add_argument("--ops", default=",".join(ALL_OPS))
    return p.parse_args()


def import_reference(ref_dir):
    """Import the reference generator from `ref_dir` without building its CUDA extensions.

    `gans/models/ops/fused_act/fused_act.py` JIT-compiles a CUDA kernel at import time with
    `torch.utils.cpp_extension.load`; on the CPU its `fused_leaky_relu` never calls that kernel
    (it takes the plain `F.leaky_relu` branch), so a stand-in `load` that returns a dummy module
    is enough. Nothing else of the reference is changed.
    """
    import torch.utils.cpp_extension as cpp_ext

    real_load = cpp_ext.load
    cpp_ext.load = lambda *a, **k: types.SimpleNamespace(fused_bias_act=None)
    sys.path.insert(0, os.path.abspath(ref_dir))
    try:
        from gans.models import dusty_v2  # noqa: E402
    finally:
        cpp_ext.load = real_load
    return dusty_v2


def load_config(ref_dir):
    import yaml

    with open(os.path.join(ref_dir, "configs", "gans", "dusty_v2.yaml")) as f:
        cfg = yaml.safe_load(f)
    return cfg["model"]["generator"]


def kitti_angles(ref_dir, h, w):
    """The reference's KITTI angle table [1, 2, H, W] resampled to h x w (bilinear on sin/cos,
    circular along azimuth, then atan2), as the reference's data pipeline does."""
    import numpy as np
    import torch
    import torch.nn.functional as F

    a = torch.from_numpy(np.load(os.path.join(ref_dir, "data", "coords", "kitti_raw.npy")))
    a = a.permute(2, 0, 1)[None]  # [1, 2, H0, W0]
    p = torch.cat([a.sin(), a.cos()], dim=1)
    p = torch.cat([p, p, p], dim=3)
    p = F.interpolate(p, size=(h, 3 * w), mode="bilinear", align_corners=False)[..., w : 2 * w]
    return torch.atan2(p[:, :2], p[:, 2:])


def main():
    args = parse_args()
    import torch

    torch.set_num_threads(args.threads)
    torch.set_num_interop_threads(1)
    torch.manual_seed(0)

    dusty_v2 = import_reference(args.reference)
    gcfg = load_config(args.reference)
    G = dusty_v2.Generator(
        mapping_kwargs=gcfg["mapping_kwargs"],
        synthesis_kwargs=gcfg["synthesis_kwargs"],
        measurement_kwargs=gcfg["measurement_kwargs"],
    ).eval()
    S = G.synthesis_network
    H, W = gcfg["synthesis_kwargs"]["resolution"]
    angle1 = kitti_angles(args.reference, H, W)
    n_params = sum(p.numel() for p in G.parameters())
    d_w = gcfg["mapping_kwargs"]["out_ch"]

    def synth(w):
        ws = w[:, None].expand(-1, S.num_styles, -1)  # same w for every layer
        angle = angle1.expand(w.shape[0], -1, -1, -1)
        return S(ws, angle)

    def times(reps, f):
        """(wall, process CPU) seconds of `reps` calls after one warm-up."""
        f()  # warm-up
        wall, cpu = [], []
        for _ in range(reps):
            s, c = time.perf_counter(), time.process_time()
            f()
            wall.append(time.perf_counter() - s)
            cpu.append(time.process_time() - c)
        return wall, cpu

    def set_weights_grad(flag):
        for p in G.parameters():
            p.requires_grad_(flag)

    def plain(batch, backward):
        set_weights_grad(backward)

        def step():
            w = torch.randn(batch, d_w)
            if backward:
                w.requires_grad_(True)
                o = synth(w)
                loss = o["image"].sum() + o["raydrop_logit"].sum()
                loss.backward()
                float(w.grad.sum())
                G.zero_grad(set_to_none=True)
            else:
                with torch.no_grad():
                    o = synth(w)
                    float(o["image"].sum() + o["raydrop_logit"].sum())

        return times(args.reps, step)

    def inversion(tune_weights):
        set_weights_grad(tune_weights)
        target = torch.randn(1, 1, H, W)
        w = torch.nn.Parameter(torch.randn(1, d_w))
        params = [w] + (list(G.parameters()) if tune_weights else [])
        opt = torch.optim.Adam(params, lr=5e-4 if tune_weights else 0.05, betas=(0.9, 0.999))

        def step():
            opt.zero_grad(set_to_none=True)
            o = synth(w)
            loss = (o["image"] - target).abs().mean()
            loss.backward()
            opt.step()
            float(w.detach().sum())

        return times(args.reps, step)

    result = {
        "impl": f"dusty-gan-v2 (PyTorch {torch.__version__})",
        "threads": torch.get_num_threads(),
        "params": n_params,
    }
    for op in args.ops.split(","):
        if op == "fwd_b1":
            t = plain(1, False)
        elif op == "fwd_b8":
            t = plain(8, False)
        elif op == "fwdbwd_b1":
            t = plain(1, True)
        elif op == "fwdbwd_b8":
            t = plain(8, True)
        elif op == "inv_w_b1":
            t = inversion(False)
        elif op == "pti_b1":
            t = inversion(True)
        else:
            raise SystemExit(f"unknown op {op}; known: {ALL_OPS}")
        result[op] = [round(x, 5) for x in t[0]]
        result[op + "_cpu"] = [round(x, 5) for x in t[1]]
    print(json.dumps(result))


if __name__ == "__main__":
    main()
