"""Ray drop inside surfaces, per class: how often a ray is lost between two returns of the
same class, in rendered training sets and in real labelled scans.

Each cloud is laid on a 64 x 512 grid (ring as row, azimuth as column). An empty pixel whose
nearest returns to the left and right in its row (each within 3 columns) carry the same class
counts as a drop of that class; the rate is such drops over such drops plus the class's
returns. Sky and open space beyond the sensor's reach are not enclosed, so they do not count.
Both sides are measured the same way; real scans with more columns than 512 lose a few
drops to pixels that two rays share.

    python3 drop_by_class.py NAME=FILE[,FILE...] ...    (needs the mcap and mcap-ros2-support
                                                         packages of tests/py/requirements.txt)
"""
import math
import struct
import sys
from collections import defaultdict

from mcap.reader import make_reader
from mcap_ros2.decoder import DecoderFactory

CLASSES = {10: "car", 30: "person", 40: "road", 48: "sidewalk", 50: "building",
           70: "vegetation", 80: "pole"}
ROWS, COLUMNS, REACH = 64, 512, 3
# sensor_msgs/PointField datatypes -> struct codes
CODES = {1: "b", 2: "B", 3: "h", 4: "H", 5: "i", 6: "I", 7: "f", 8: "d"}


def grids(path):
    """Each scan of `path` as a ROWS x COLUMNS grid of labels (-1: no return)."""
    with open(path, "rb") as f:
        reader = make_reader(f, decoder_factories=[DecoderFactory()])
        for _, _, _, msg in reader.iter_decoded_messages(topics=["/velodyne_points"]):
            fields = {fd.name: fd for fd in msg.fields}
            names = ["x", "y", "ring", "label"]
            layout = sorted((fields[n].offset, n) for n in names)
            fmt, at = "<", 0
            for offset, n in layout:
                fmt += "x" * (offset - at) + CODES[fields[n].datatype]
                at = offset + struct.calcsize("<" + CODES[fields[n].datatype])
            fmt += "x" * (msg.point_step - at)
            order = [n for _, n in layout]
            grid = [[-1] * COLUMNS for _ in range(ROWS)]
            for values in struct.iter_unpack(fmt, bytes(msg.data)):
                p = dict(zip(order, values))
                ring = int(p["ring"])
                if not 0 <= ring < ROWS:
                    continue
                az = math.atan2(p["y"], p["x"])
                col = int((math.pi - az) / (2 * math.pi) * COLUMNS) % COLUMNS
                grid[ring][col] = int(p["label"]) & 0xFFFF
            yield grid


def nearest(row, c, step):
    """The label of the first return from column `c` in direction `step` within REACH."""
    labels = (row[(c + step * d) % COLUMNS] for d in range(1, REACH + 1))
    return next((label for label in labels if label >= 0), None)


def tally(path, counts):
    for grid in grids(path):
        for row in grid:
            for c, label in enumerate(row):
                if label >= 0:
                    if label in CLASSES:
                        counts[label][0] += 1
                    continue
                left, right = nearest(row, c, -1), nearest(row, c, 1)
                if left is not None and left == right and left in CLASSES:
                    counts[left][1] += 1


def main():
    print("| set | " + " | ".join(CLASSES.values()) + " |")
    print("|---|" + "---|" * len(CLASSES))
    for arg in sys.argv[1:]:
        name, files = arg.split("=", 1)
        counts = defaultdict(lambda: [0, 0])
        for path in files.split(","):
            tally(path, counts)
        cells = []
        for label in CLASSES:
            kept, dropped = counts[label]
            cells.append(f"{100 * dropped / (kept + dropped):.1f}" if kept + dropped else "-")
        print(f"| {name} | " + " | ".join(cells) + " |", flush=True)


if __name__ == "__main__":
    main()
