#!/usr/bin/env python3
"""Convert a dataset of MCAP recordings on a Ray cluster with rangegan-mcap.

    python python/rangegan_ray.py IN_DIR OUT_DIR [--address HOST:PORT] [--binary PATH]
        [--retries N] [--cpus-per-task N] -- [convert options, e.g. --quality off]

The binary itself lists the dataset and decides what is up to date (`convert --dry-run`
against OUT_DIR/rangegan-manifest.jsonl); one Ray task per remaining file runs the
binary's one-file form on that file and returns its manifest line; this driver alone
appends the lines (one write + fsync each), so the manifest is the same format as a
single-machine `convert IN_DIR OUT_DIR` and either can resume the other's run. A task
whose worker dies is retried by Ray (bounded by --retries); a file the binary refuses
(a corrupt recording) is recorded as failed and not retried. Outputs are written
atomically by the binary, so a retried file never leaves a partial or duplicate output.

Every node needs the binary at the same path and IN_DIR / OUT_DIR on a shared volume.
Exit code: 0 when every file is converted or up to date, 4 when some failed.
"""

import argparse
import json
import os
import signal
import subprocess
import sys
import time

import ray

MANIFEST = "rangegan-manifest.jsonl"


def plan(binary, in_dir, out_dir, convert_args):
    """The files of the dataset and what to do with each, as the binary sees it."""
    cmd = [binary, "--json", "--quiet", "convert", in_dir, out_dir, "--dry-run", *convert_args]
    done = subprocess.run(cmd, capture_output=True, text=True, check=False)
    if done.returncode != 0:
        sys.exit(f"error: {' '.join(cmd)}: {done.stderr.strip()}")
    return json.loads(done.stdout)["files"]


def _die_with_parent():
    """The binary ends when the worker running it dies (Linux), so a retried task is the
    only writer of its file."""
    try:
        import ctypes

        ctypes.CDLL("libc.so.6").prctl(1, signal.SIGKILL)  # PR_SET_PDEATHSIG
    except OSError:
        pass


@ray.remote
def convert_file(binary, in_dir, rel, out_dir, convert_args, threads):
    """Runs the one-file form on `rel` and returns its manifest line (status failed when
    the binary refused the file). The input is named by its relative path, so the output
    is the same bytes as in a single-machine run of the whole folder. The binary uses
    `threads` threads (the task's CPUs) unless the convert options set `--threads`."""
    output = os.path.join(out_dir, rel)
    os.makedirs(os.path.dirname(output) or ".", exist_ok=True)
    threads = [] if "--threads" in convert_args else ["--threads", str(threads)]
    cmd = [binary, "--json", "--quiet", *threads, "convert", rel, output, "--force", *convert_args]
    started = time.monotonic()
    done = subprocess.run(
        cmd, cwd=in_dir, capture_output=True, text=True, check=False, preexec_fn=_die_with_parent
    )
    if done.returncode < 0:
        # Killed by a signal (out of memory, a node going away): let Ray retry it.
        raise RuntimeError(f"{rel}: rangegan-mcap killed by signal {-done.returncode}")
    if done.returncode in (0, 3):
        entry = json.loads(done.stdout)["manifest"]
        entry["output"] = rel
        return entry
    return failed_entry(os.path.join(in_dir, rel), rel, done.stderr.strip(),
                        time.monotonic() - started)


def failed_entry(path, rel, error, seconds=0.0):
    """A manifest line for a file that was not converted (same fields as the binary's)."""
    size = os.path.getsize(path) if os.path.exists(path) else 0
    return {"input": rel, "input_size": size, "input_hash": "", "output": rel,
            "output_size": None, "output_hash": None, "status": "failed", "error": error,
            "records_copied": 0, "scans": 0, "malformed": 0, "warnings": 0,
            "seconds": seconds, "tool": "rangegan-mcap", "version": "", "args": ""}


class ManifestWriter:
    """Appends lines to the manifest, one write + fsync each; a torn last line left by a
    killed driver is cut off first (as the binary does)."""

    def __init__(self, path):
        with open(path, "ab+") as f:
            f.seek(0)
            text = f.read()
            if text and not text.endswith(b"\n"):
                f.truncate(text.rfind(b"\n") + 1)
        self.file = open(path, "ab")

    def append(self, entry):
        self.file.write((json.dumps(entry, separators=(",", ":")) + "\n").encode())
        self.file.flush()
        os.fsync(self.file.fileno())


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("in_dir")
    parser.add_argument("out_dir")
    parser.add_argument("--address", default=None, help="Ray cluster (default: RAY_ADDRESS or a local one)")
    parser.add_argument("--binary", default="rangegan-mcap", help="rangegan-mcap on every node")
    parser.add_argument("--retries", type=int, default=3, help="retries of a task whose worker died")
    parser.add_argument("--cpus-per-task", type=float, default=1,
                        help="CPUs Ray reserves per file; also the binary's --threads")
    argv = list(sys.argv[1:] if argv is None else argv)
    split = argv.index("--") if "--" in argv else len(argv)
    args = parser.parse_args(argv[:split])
    convert_args = argv[split + 1:]  # after `--`: options of `rangegan-mcap convert`
    binary = args.binary if os.sep not in args.binary else os.path.abspath(args.binary)
    in_dir, out_dir = os.path.abspath(args.in_dir), os.path.abspath(args.out_dir)

    started = time.monotonic()
    files = plan(binary, in_dir, out_dir, convert_args)
    todo = [f["input"] for f in files if f["action"] != "skip"]
    print(f"{len(files)} files: {len(todo)} to convert, {len(files) - len(todo)} up to date",
          file=sys.stderr)
    if not todo:
        return 0
    os.makedirs(out_dir, exist_ok=True)
    manifest = ManifestWriter(os.path.join(out_dir, MANIFEST))

    if __name__ != "__main__":
        # Imported (e.g. by a test): ship this module's code to the workers with the task.
        ray.cloudpickle.register_pickle_by_value(sys.modules[__name__])
    if not ray.is_initialized():  # a caller may have connected already
        ray.init(address=args.address, logging_level="ERROR", log_to_driver=False)
    task = convert_file.options(num_cpus=args.cpus_per_task, max_retries=args.retries,
                                retry_exceptions=True)
    threads = max(1, int(args.cpus_per_task))
    pending = {task.remote(binary, in_dir, rel, out_dir, convert_args, threads): rel
               for rel in todo}
    failed = 0
    while pending:
        ready, _ = ray.wait(list(pending), num_returns=1)
        rel = pending.pop(ready[0])
        try:
            entry = ray.get(ready[0])
        except Exception as e:  # retries exhausted
            entry = failed_entry(os.path.join(in_dir, rel), rel, str(e))
        failed += entry["status"] != "ok"
        manifest.append(entry)
        print(f"{rel}: {entry['status']}", file=sys.stderr)
    ray.shutdown()
    secs = time.monotonic() - started
    print(f"{len(todo)} converted ({failed} failed) in {secs:.1f} s", file=sys.stderr)
    return 4 if failed else 0


if __name__ == "__main__":
    sys.exit(main())
