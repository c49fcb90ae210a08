"""The Sim2Real table per place and pooled, from `segment eval --json` files laid out as
DIR/CONFIG-sSEED/PLACE.json (places.sh writes them).

Pooled scores add the places' counts (labelled, predicted and correct returns per class)
before dividing, so a place weighs by its labelled returns. The interval is a bootstrap over
places and seeds: each draw takes places with replacement (the same places for every
config, so differences are paired) and, per config, seeds with replacement.

    python3 places.py DIR [--draws 2000] [--seed 0]
"""
import argparse
import json
import random
from collections import defaultdict
from pathlib import Path

CONFIGS = ["A", "B", "C", "E", "Es", "F", "G", "real", "real_boxes", "real_boxes_lopo"]
DESCRIPTION = {
    "A": "no ray drop",
    "B": "global drop frequency",
    "C": "per-pixel drop frequency",
    "E": "GAN x_n",
    "Es": "GAN x_n, sharpened (`--drop-sharpness 8`)",
    "F": "physics fitted by `diagnose`",
    "G": "F's perturbations, GAN ray drop",
    "real": "trained on real scans (oracle)",
    "real_boxes": "real scans + KITTI object boxes (oracle)",
    "real_boxes_lopo": "real_boxes trained on every place but the one scored (oracle)",
}
ORACLES = ("real", "real_boxes", "real_boxes_lopo")
SCORED = ["car", "person", "road", "sidewalk", "building", "vegetation", "pole"]
# Places whose unlabelled scans trained the generator behind E's, Es's and G's ray drop.
GAN_CONFIGS = ("E", "Es", "G")
GAN_SAW = {"01", "02", "03", "04", "05", "06", "09", "10"}


def load(root):
    """{config: {seed: {place: {class: (points, predicted, correct)}}}}"""
    runs = defaultdict(lambda: defaultdict(dict))
    for run in sorted(Path(root).iterdir()):
        if not run.is_dir():
            continue
        config, seed = run.name.rsplit("-s", 1)
        for path in sorted(run.glob("*.json")):
            report = json.loads(path.read_text())
            runs[config][seed][path.stem] = {
                c["class"]: (c["points"], c["predicted"], c["correct"]) for c in report["classes"]
            }
    return runs


def miou(counts, classes=SCORED):
    """Mean IoU over `classes` with labelled returns, from summed counts; None if none."""
    ious = []
    for c in classes:
        points, predicted, correct = counts.get(c, (0, 0, 0))
        if points > 0:
            ious.append(correct / (points + predicted - correct))
    return 100 * sum(ious) / len(ious) if ious else None


def iou(counts, c):
    points, predicted, correct = counts.get(c, (0, 0, 0))
    union = points + predicted - correct
    return 100 * correct / union if union > 0 else None


def pooled(per_place, places):
    """The counts of `places` summed (places missing from `per_place` are left out)."""
    total = defaultdict(lambda: [0, 0, 0])
    for p in places:
        for c, counts in per_place.get(p, {}).items():
            for k in range(3):
                total[c][k] += counts[k]
    return {c: tuple(v) for c, v in total.items()}


def seed_mean(runs, config, places, score=miou):
    values = [score(pooled(per_place, places)) for per_place in runs[config].values()]
    values = [v for v in values if v is not None]
    return sum(values) / len(values) if values else None


def fmt(v):
    return "-" if v is None else f"{v:.1f}"


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("root")
    ap.add_argument("--draws", type=int, default=2000)
    ap.add_argument("--seed", type=int, default=0)
    args = ap.parse_args()
    runs = load(args.root)
    configs = [c for c in CONFIGS if c in runs]
    places = sorted({p for c in configs for s in runs[c].values() for p in s})
    seeds = {c: sorted(runs[c]) for c in configs}

    print("mIoU (%, 7 classes) per place, mean over seeds; `*`: the generator behind E's, Es's and")
    print("G's ray drop trained on that place's unlabelled scans.")
    print()
    print("| place | " + " | ".join(configs) + " |")
    print("|---|" + "---|" * len(configs))
    for p in places:
        row = []
        for c in configs:
            v = fmt(seed_mean(runs, c, [p]))
            row.append(v + ("*" if c in GAN_CONFIGS and p in GAN_SAW and v != "-" else ""))
        print(f"| {p} | " + " | ".join(row) + " |")

    rng = random.Random(args.seed)
    draws = defaultdict(list)
    for _ in range(args.draws):
        sample = [rng.choice(places) for _ in places]
        for c in configs:
            chosen = [rng.choice(seeds[c]) for _ in seeds[c]]
            values = [miou(pooled(runs[c][s], sample)) for s in chosen]
            values = [v for v in values if v is not None]
            draws[c].append(sum(values) / len(values) if values else None)

    def interval(values):
        values = sorted(v for v in values if v is not None)
        if not values:
            return "-"
        lo, hi = values[int(0.025 * len(values))], values[int(0.975 * len(values)) - 1]
        return f"{lo:.1f} to {hi:.1f}"

    print()
    print(f"Pooled over the {len(places)} places ({args.draws} bootstrap draws over places and seeds):")
    print()
    print("| config | what | seeds | mIoU | 95 % interval | - A | interval of - A | person IoU | "
          "mIoU on 00 and 07 |")
    print("|---|---|---|---|---|---|---|---|---|")
    for c in configs:
        point = seed_mean(runs, c, places)
        diff, diff_iv = "-", "-"
        if c != "A" and "A" in runs:
            a = seed_mean(runs, "A", places)
            diff = fmt(point - a) if point is not None and a is not None else "-"
            diff_iv = interval(
                [x - y for x, y in zip(draws[c], draws["A"]) if x is not None and y is not None])
        person = seed_mean(runs, c, places, score=lambda counts: iou(counts, "person"))
        clean = seed_mean(runs, c, [p for p in places if p in ("00", "07")])
        print(f"| {c} | {DESCRIPTION[c]} | {len(seeds[c])} | {fmt(point)} | {interval(draws[c])} | "
              f"{diff} | {diff_iv} | {fmt(person)} | {fmt(clean)} |")

    for e in ("E", "Es"):
        if e not in runs or "C" not in runs:
            continue
        diffs = [x - y for x, y in zip(draws[e], draws["C"]) if x is not None and y is not None]
        point = seed_mean(runs, e, places) - seed_mean(runs, "C", places)
        print()
        print(f"{e} - C (the generator's x_n against the real per-pixel frequency): {point:.1f} "
              f"(interval {interval(diffs)}).")

    sims = [c for c in configs if c not in ORACLES]
    best = max(sims, key=lambda c: seed_mean(runs, c, places) or -1)
    for oracle in (o for o in ORACLES if o in runs):
        ratio = [x / y for x, y in zip(draws[best], draws[oracle]) if x and y]
        point = seed_mean(runs, best, places) / seed_mean(runs, oracle, places)
        ratio_sorted = sorted(ratio)
        lo, hi = ratio_sorted[int(0.025 * len(ratio))], ratio_sorted[int(0.975 * len(ratio)) - 1]
        print()
        print(f"Best simulated config {best}: {100 * point:.0f} % of the oracle {oracle} "
              f"(interval {100 * lo:.0f}-{100 * hi:.0f} %).")

    print()
    print("IoU per class (%), pooled over the places, mean over seeds:")
    print()
    print("| config | " + " | ".join(SCORED) + " |")
    print("|---|" + "---|" * len(SCORED))
    for c in configs:
        row = [fmt(seed_mean(runs, c, places, score=lambda counts, k=k: iou(counts, k))) for k in SCORED]
        print(f"| {c} | " + " | ".join(row) + " |")


if __name__ == "__main__":
    main()
