"""Aggregate `segment eval --json` files named CONFIG-sSEED.json into a markdown table:
mean +- sd over seeds of car and person precision/recall/IoU, their mean IoU (the paper's
Table 4) and the mean IoU over all named classes (whole revolutions, and the frontal 90 degrees
the paper scored), beside the paper's numbers."""
import json
import statistics
import sys
from collections import defaultdict
from pathlib import Path

DESCRIPTION = {
    "A": "Simulation, no ray drop",
    "B": "+ global drop frequency",
    "C": "+ per-pixel drop frequency",
    "E": "+ GAN auto-decoded x_n",
    "Es": "+ GAN x_n, sharpened",
    "F": "+ physics fitted by `diagnose`",
    "G": "+ fitted perturbations, GAN ray drop",
    "real": "Real (oracle)",
    "real_boxes": "Real + KITTI object boxes (oracle)",
}
# The paper's Table 4: car IoU, pedestrian IoU, mIoU (SqueezeSegV2, GTA-LiDAR -> KITTI-frontal).
PAPER = {"A": (1.1, 2.4, 1.7), "B": (55.2, 25.1, 40.2), "C": (59.0, 22.5, 40.7),
         "E": (67.3, 25.2, 46.3), "real": (70.1, 16.5, 43.3)}


def stat(values):
    values = [100 * v for v in values if v is not None]
    if not values:
        return "-"
    if len(values) == 1:
        return f"{values[0]:.1f}"
    return f"{statistics.mean(values):.1f} ± {statistics.stdev(values):.1f}"


runs = defaultdict(list)
for path in sorted(Path(sys.argv[1]).glob("*.json")):
    config = path.stem.rsplit("-s", 1)[0]
    runs[config].append(json.loads(path.read_text()))

classes = [c["class"] for c in next(iter(runs.values()))[0]["classes"] if c["class"] != "other"]
head = ["config", "training data", "seeds", "car P", "car R", "car IoU", "person P", "person R",
        "person IoU", "mIoU car+person", "paper car / person / mIoU", "mIoU 7 classes",
        "frontal mIoU 7 classes"]
print("| " + " | ".join(head) + " |")
print("|" + "---|" * len(head))
for config in [c for c in DESCRIPTION if c in runs]:
    reports = runs[config]
    cls = lambda name, key: stat([next(c for c in r["classes"] if c["class"] == name)[key] for r in reports])
    paper = PAPER.get(config)
    row = [config, DESCRIPTION[config], str(len(reports)),
           cls("car", "precision"), cls("car", "recall"), cls("car", "iou"),
           cls("person", "precision"), cls("person", "recall"), cls("person", "iou"),
           stat([r["miou_car_person"] for r in reports]),
           " / ".join(map(str, paper)) if paper else "-",
           stat([r["miou"] for r in reports]),
           stat([r["frontal"]["miou"] for r in reports])]
    print("| " + " | ".join(row) + " |")
print()
print("IoU per class (%, mean ± sd over seeds):")
print()
print("| config | " + " | ".join(classes) + " |")
print("|---|" + "---|" * len(classes))
for config in [c for c in DESCRIPTION if c in runs]:
    reports = runs[config]
    row = [stat([next(c for c in r["classes"] if c["class"] == name)["iou"] for r in reports]) for name in classes]
    print(f"| {config} | " + " | ".join(row) + " |")
