"""Dataset throughput: `convert --jobs 1`, `--jobs 2` and the Ray driver with 2 workers
(a local head node and a second node, one CPU each) on the same folder of small simulated
recordings, measured side by side in one run.

    .venv/bin/python benches/dataset_scale_out.py BINARY WORK_DIR [FILES] [SCANS] [QUALITY]

QUALITY: `off` (default; range images only) or `fast` (the auto-decoding).

Prints one JSON line per method: files/s, scans/s, and for Ray the driver's overhead per
file (its wall time minus that of `--jobs 2`, per file).
"""

import json
import os
import shutil
import subprocess
import sys
import time

HERE = os.path.dirname(os.path.abspath(__file__))
sys.path[:0] = [os.path.join(HERE, "..", "tests", "py"), os.path.join(HERE, "..", "python")]
import rangegan_ray  # noqa: E402
import test_ray  # noqa: E402


def make_dataset(binary, root, files, scans):
    for i in range(files):
        path = os.path.join(root, f"day{i % 4}", f"drive{i:03}.mcap")
        if not os.path.exists(path):
            os.makedirs(os.path.dirname(path), exist_ok=True)
            subprocess.run([binary, "-q", "simulate", "--scene", str(i), "--scans", str(scans),
                            "--sensor", "vlp16", path], check=True)


def timed(fn):
    started = time.monotonic()
    fn()
    return time.monotonic() - started


def main():
    binary, work = os.path.abspath(sys.argv[1]), os.path.abspath(sys.argv[2])
    files = int(sys.argv[3]) if len(sys.argv) > 3 else 120
    scans = int(sys.argv[4]) if len(sys.argv) > 4 else 5
    quality = sys.argv[5] if len(sys.argv) > 5 else "off"
    args = ["--quality", quality]
    root = os.path.join(work, "in")
    make_dataset(binary, root, files, scans)
    results = {}
    print(json.dumps({"quality": quality}))
    for jobs in (1, 2):
        out = os.path.join(work, f"jobs{jobs}")
        shutil.rmtree(out, ignore_errors=True)
        cmd = [binary, "-q", "convert", root, out, "--jobs", str(jobs), *args]
        results[f"jobs{jobs}"] = timed(lambda: subprocess.run(cmd, check=True))
    address, nodes = test_ray.start_cluster(work)
    try:
        out = os.path.join(work, "ray")
        shutil.rmtree(out, ignore_errors=True)
        argv = [root, out, "--address", address, "--binary", binary, "--", *args]
        results["ray2"] = timed(lambda: rangegan_ray.main(argv))
    finally:
        test_ray.stop_cluster(nodes)
    total_scans = files * scans
    for name, secs in results.items():
        row = {"method": name, "files": files, "scans": total_scans, "seconds": round(secs, 2),
               "files_per_s": round(files / secs, 1), "scans_per_s": round(total_scans / secs, 1)}
        if name == "ray2":
            row["driver_overhead_ms_per_file"] = round(1000 * (secs - results["jobs2"]) / files, 1)
        print(json.dumps(row))


if __name__ == "__main__":
    main()
