"""Ray drop inside surfaces: how often a ray is lost between two returns of the same surface,
in rendered training sets and in real scans. By class (labelled scans), or with `--surfaces`
by range alone, which needs no labels (so unlabelled real scans can be compared too).

Each cloud is laid on a 64 x 512 grid (ring as row, azimuth as column). An empty pixel whose
nearest returns to the left and right in its row (each within 3 columns) carry the same class
(or, with `--surfaces`, ranges within 5 % of each other) counts as a drop inside that class
(surface); the rate is such drops over such drops plus the class's (all) returns. Sky and
open space beyond the sensor's reach are not enclosed, so they do not count. Both sides are
measured the same way; real scans with more columns than 512 lose a few drops to pixels that
two rays share. `--surfaces` also prints the share of all pixels without a return.

    python3 drop_by_class.py [--surfaces] NAME=FILE[,FILE...] ...
        (needs numpy and the mcap and mcap-ros2-support packages of tests/py/requirements.txt)
"""
import sys
from collections import defaultdict

import numpy as np
from mcap.reader import make_reader
from mcap_ros2.decoder import DecoderFactory

CLASSES = {10: "car", 30: "person", 40: "road", 48: "sidewalk", 50: "building",
           70: "vegetation", 80: "pole"}
ROWS, COLUMNS, REACH = 64, 512, 3
SAME_SURFACE = 0.05  # relative range difference of the two returns around a drop
# sensor_msgs/PointField datatypes -> numpy types
TYPES = {1: "i1", 2: "u1", 3: "<i2", 4: "<u2", 5: "<i4", 6: "<u4", 7: "<f4", 8: "<f8"}


def grids(path, surfaces):
    """Each scan of `path` as a ROWS x COLUMNS grid: the label (labelled mode) or the range
    (`surfaces`) of each pixel's return, NaN where there is none."""
    with open(path, "rb") as f:
        reader = make_reader(f, decoder_factories=[DecoderFactory()])
        for _, _, _, msg in reader.iter_decoded_messages(topics=["/velodyne_points"]):
            names = ["x", "y", "z", "ring"] + ([] if surfaces else ["label"])
            fields = {fd.name: fd for fd in msg.fields}
            dtype = np.dtype({"names": names,
                              "formats": [TYPES[fields[n].datatype] for n in names],
                              "offsets": [fields[n].offset for n in names],
                              "itemsize": msg.point_step})
            points = np.frombuffer(bytes(msg.data), dtype=dtype)
            ring = points["ring"].astype(np.int64)
            x, y, z = (points[n].astype(np.float64) for n in "xyz")
            col = ((np.pi - np.arctan2(y, x)) / (2 * np.pi) * COLUMNS).astype(np.int64) % COLUMNS
            value = (np.sqrt(x * x + y * y + z * z) if surfaces
                     else (points["label"].astype(np.int64) & 0xFFFF).astype(np.float64))
            inside = (ring >= 0) & (ring < ROWS)
            grid = np.full((ROWS, COLUMNS), np.nan)
            grid[ring[inside], col[inside]] = value[inside]
            yield grid


def nearest(grid, step):
    """For each pixel, the value of the first return from it in direction `step` along its
    row within REACH columns (wrapping around the turn), NaN where there is none."""
    found = np.full(grid.shape, np.nan)
    for d in range(REACH, 0, -1):
        shifted = np.roll(grid, -step * d, axis=1)
        found = np.where(np.isnan(shifted), found, shifted)
    return found


def tally(path, counts, surfaces):
    for grid in grids(path, surfaces):
        empty = np.isnan(grid)
        left, right = nearest(grid, -1), nearest(grid, 1)
        if surfaces:
            close = np.abs(left - right) <= SAME_SURFACE * np.minimum(left, right)
            counts["surfaces"][0] += int((~empty).sum())
            counts["surfaces"][1] += int((empty & close).sum())
            counts["pixels"][0] += grid.size
            counts["pixels"][1] += int(empty.sum())
            continue
        for label in CLASSES:
            counts[label][0] += int((grid == label).sum())
            counts[label][1] += int((empty & (left == label) & (right == label)).sum())


def main():
    args = sys.argv[1:]
    surfaces = "--surfaces" in args
    args = [a for a in args if a != "--surfaces"]
    columns = {"surfaces": "inside surfaces", "pixels": "no return"} if surfaces else CLASSES
    print("| set | " + " | ".join(columns.values()) + " |")
    print("|---|" + "---|" * len(columns))
    for arg in args:
        name, files = arg.split("=", 1)
        counts = defaultdict(lambda: [0, 0])
        for path in files.split(","):
            tally(path, counts, surfaces)
        cells = []
        for key in columns:
            kept, dropped = counts[key]
            total = kept if key == "pixels" else kept + dropped
            cells.append(f"{100 * dropped / total:.1f}" if total else "-")
        print(f"| {name} | " + " | ".join(cells) + " |", flush=True)


if __name__ == "__main__":
    main()
