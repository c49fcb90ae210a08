"""Where the error of filling a missing beam lies: each beam of a dataset cache (`train
--cache`, f32 inverse depth in network units, -1 = no return) predicted from the beams above
and below, by simple vertical rules, split into smooth pixels and depth edges (the beams
above and below more than 15 % apart in depth). Analysis of headroom only; nothing is chosen
by it.

    python3 experiments/completion/beam_headroom.py RUN/dataset.bin [EVERY_NTH_SCAN]

Needs numpy.
"""
import json
import struct
import sys

import numpy as np

EDGE_LOG_RATIO = 0.15


def load(path):
    b = open(path, 'rb').read()
    at = 8
    profile = {}
    if b[:8] == b'RGDSv002':
        n = struct.unpack_from('<Q', b, 8)[0]
        profile = json.loads(b[16:16 + n])
        at += 8 + n
    elif b[:8] != b'RGDSv001':
        sys.exit(f'{path}: not a dataset cache (bad magic)')
    n, h, w = struct.unpack_from('<3Q', b, at)
    at += 24
    elevation = np.frombuffer(b, '<f4', h * w, at).reshape(h, w)
    at += 8 * h * w  # elevation, then azimuth
    x = np.frombuffer(b, '<f4', n * h * w, at).reshape(n, h, w)
    min_m = profile.get('min_range_m', 1.45)
    with np.errstate(divide='ignore'):
        depth = np.where(x > -0.999, 2 * min_m / (x + 1), 0.0)
    return depth, elevation


def main():
    depth, elevation = load(sys.argv[1])
    depth = depth[::int(sys.argv[2]) if len(sys.argv) > 2 else 5]
    up, mid, down = depth[:, :-2], depth[:, 1:-1], depth[:, 2:]
    e_up, e_mid, e_down = elevation[:-2], elevation[1:-1], elevation[2:]
    ok = (up > 0) & (mid > 0) & (down > 0)
    safe_up, safe_down = up.clip(1e-3), down.clip(1e-3)
    t = (e_up - e_mid) / (e_up - e_down)
    s = (np.sin(e_up) - np.sin(e_mid)) / (np.sin(e_up) - np.sin(e_down))
    rules = {
        'column, by row index': 0.5 * (up + down),
        'column, by elevation': (1 - t) * up + t * down,
        'inverse depth, by sin(elevation)': 1 / ((1 - s) / safe_up + s / safe_down),
        'the nearer side': np.minimum(up, down),
        'the right side (oracle)': np.where(np.abs(up - mid) < np.abs(down - mid), up, down),
    }
    edge = ok & (np.abs(np.log(safe_up / safe_down)) > EDGE_LOG_RATIO)
    smooth = ok & ~edge
    print(f'{ok.sum()} pixels, {edge.sum() / ok.sum():.1%} at depth edges')
    print('| rule | MAE (m) | smooth pixels | edges | share of the error at edges |')
    print('|---|---|---|---|---|')
    for name, guess in rules.items():
        err = np.abs(guess - mid)
        print(f'| {name} | {err[ok].mean():.3f} | {err[smooth].mean():.3f} | '
              f'{err[edge].mean():.3f} | {err[edge].sum() / err[ok].sum():.0%} |')


main()
