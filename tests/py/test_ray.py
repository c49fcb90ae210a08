"""The Ray driver (python/rangegan_ray.py) on a real local Ray cluster: a head node on
127.0.0.1 and a second node, one CPU each. Run by tests/ray.rs:

    python tests/py/test_ray.py BINARY IN_DIR SINGLE_OUT_DIR WORK_DIR

IN_DIR holds the dataset, SINGLE_OUT_DIR the single-process `convert` of it (same
convert options as CONVERT_ARGS below). Checks: outputs byte-identical to the
single-process run, a worker killed mid-run loses or duplicates no file, and a rerun
after completion converts nothing.
"""

import json
import os
import signal
import socket
import subprocess
import sys
import threading
import time

HERE = os.path.dirname(os.path.abspath(__file__))
sys.path.insert(0, os.path.join(HERE, "..", "..", "python"))
import rangegan_ray  # noqa: E402

CONVERT_ARGS = ["--quality", "off"]


def free_port():
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def start_cluster(work):
    """A head node and a worker node, each a `ray start --block` we own and stop by pid."""
    ray = os.path.join(os.path.dirname(sys.executable), "ray")
    port = free_port()
    env = dict(os.environ, RAY_USAGE_STATS_ENABLED="0")
    common = ["--num-cpus", "1", "--block", "--disable-usage-stats"]
    head = subprocess.Popen(
        [ray, "start", "--head", "--node-ip-address", "127.0.0.1", "--port", str(port),
         "--include-dashboard", "false", "--temp-dir", os.path.join(work, "ray"), *common],
        env=env, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL, start_new_session=True)
    address = f"127.0.0.1:{port}"
    import ray as ray_api
    for _ in range(120):  # wait for the head
        try:
            ray_api.init(address=address, logging_level="ERROR", log_to_driver=False)
            break
        except Exception:
            time.sleep(0.5)
    else:
        raise RuntimeError("Ray head did not start")
    worker = subprocess.Popen(
        [ray, "start", "--address", address, "--node-ip-address", "127.0.0.1", *common],
        env=env, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL, start_new_session=True)
    for _ in range(120):
        if len([n for n in ray_api.nodes() if n["Alive"]]) == 2:
            break
        time.sleep(0.5)
    else:
        raise RuntimeError("Ray worker node did not join")
    return address, [head, worker]  # still connected: the driver reuses the connection


def stop_cluster(nodes):
    for p in reversed(nodes):
        os.killpg(p.pid, signal.SIGTERM)  # the process groups we started, nothing else
    for p in reversed(nodes):
        try:
            p.wait(timeout=30)
        except subprocess.TimeoutExpired:
            os.killpg(p.pid, signal.SIGKILL)


def tree(root):
    out = {}
    for d, _, files in os.walk(root):
        for f in files:
            if f.endswith(".mcap"):
                p = os.path.join(d, f)
                with open(p, "rb") as fh:
                    out[os.path.relpath(p, root)] = fh.read()
    return out


def manifest(out):
    with open(os.path.join(out, "rangegan-manifest.jsonl")) as f:
        return [json.loads(line) for line in f]


def kill_one_worker(killed, stop):
    """SIGKILLs the first Ray worker seen running a conversion (the binary dies with it)."""
    while not stop.is_set() and not killed:
        for pid in os.listdir("/proc"):
            if not pid.isdigit():
                continue
            try:
                with open(f"/proc/{pid}/cmdline", "rb") as f:
                    cmd = f.read()
            except OSError:
                continue
            if cmd.startswith(b"ray::convert_file"):
                os.kill(int(pid), signal.SIGKILL)
                killed.append(int(pid))
                return
        time.sleep(0.005)


def drive(binary, in_dir, out, address):
    argv = [in_dir, out, "--address", address, "--binary", binary, "--retries", "3", "--",
            *CONVERT_ARGS]
    return rangegan_ray.main(argv)


def main():
    binary, in_dir, single, work = sys.argv[1:5]
    expected = tree(single)
    assert len(expected) == 12, sorted(expected)
    address, nodes = start_cluster(work)
    killed, stop = [], threading.Event()
    try:
        # A worker killed mid-run: its file is retried, none lost, none twice.
        out = os.path.join(work, "ray_out")
        killer = threading.Thread(target=kill_one_worker, args=(killed, stop), daemon=True)
        killer.start()
        try:
            code = drive(binary, in_dir, out, address)
        finally:
            stop.set()
        killer.join()
        assert code == 0, code
        assert killed, "no worker was running a conversion to kill"
        lines = manifest(out)
        inputs = [line["input"] for line in lines]
        assert sorted(inputs) == sorted(expected), inputs
        assert all(line["status"] == "ok" for line in lines), lines
        got = tree(out)
        assert got.keys() == expected.keys(), sorted(got)
        for rel, data in expected.items():
            assert got[rel] == data, f"{rel}: Ray output differs from the single-process run"
        # The binary reads the driver's manifest: nothing left to do for it either.
        dry = subprocess.run([binary, "--json", "convert", in_dir, out, "--dry-run",
                              *CONVERT_ARGS], capture_output=True, text=True, check=True)
        assert all(f["action"] == "skip" for f in json.loads(dry.stdout)["files"]), dry.stdout

        # A rerun after completion does nothing.
        before = {p: os.stat(os.path.join(out, p)).st_mtime_ns for p in got}
        with open(os.path.join(out, "rangegan-manifest.jsonl"), "rb") as f:
            manifest_before = f.read()
        assert drive(binary, in_dir, out, address) == 0
        with open(os.path.join(out, "rangegan-manifest.jsonl"), "rb") as f:
            assert f.read() == manifest_before
        assert before == {p: os.stat(os.path.join(out, p)).st_mtime_ns for p in got}
        print(f"ok: 12 files, killed worker pid {killed[0]}, outputs identical, rerun idle")
    finally:
        stop_cluster(nodes)


if __name__ == "__main__":
    main()
