#!/usr/bin/env python3
"""Runs the workspace's test binaries as `cargo test --workspace --no-fail-fast` would, but in two lanes side by
side: the end-to-end binary (tests/e2e, most of the run's time, much of it waiting on servers and simulators) in
one, every other test binary one after another in the other, then the doc-tests. cargo runs the binaries one at a
time, so the other crates' tests (the simulator worker's among them, minutes of stepping every task) used to wait
for the end-to-end binary to finish.

Each binary runs as cargo runs it: from its package's folder, with cargo's run-time variables (CARGO,
CARGO_MANIFEST_DIR, CARGO_PKG_NAME, CARGO_PKG_VERSION, CARGO_CRATE_NAME). The end-to-end binary's output streams as
it comes; every other binary's is printed whole when it ends, after cargo's own "Running ..." line, so the two
lanes never interleave within a binary. Exits 1 if any binary failed, after all have run (--no-fail-fast).

Usage: scripts/run-tests.py [cargo test options, e.g. --locked]   (after the test build: scripts/test.sh)
"""
import json
import os
import shutil
import subprocess
import sys
import threading

E2E_PACKAGE = "dsrl-e2e"
E2E_TARGET = "e2e"

printing = threading.Lock()


def test_binaries(cargo, options):
    """The test executables `cargo test --workspace` runs, in its order (built already: this compiles nothing)."""
    listed = subprocess.run(
        [cargo, "test", *options, "--workspace", "--no-run", "--message-format=json-render-diagnostics"],
        stdout=subprocess.PIPE, check=True, text=True)
    binaries = []
    for line in listed.stdout.splitlines():
        message = json.loads(line)
        if message.get("reason") != "compiler-artifact" or not message.get("executable"):
            continue
        if not message["profile"]["test"]:
            continue
        target = message["target"]
        package_id = message["package_id"]
        manifest_dir = os.path.dirname(message["manifest_path"])
        binaries.append({
            "package": package_name(package_id, manifest_dir),
            "version": package_version(package_id),
            "target": target["name"],
            "kind": target["kind"][0],
            "src": os.path.relpath(target["src_path"], manifest_dir),
            "executable": message["executable"],
            "manifest_dir": manifest_dir,
        })
    # cargo's order: by package, then by target.
    binaries.sort(key=lambda b: (b["package"], b["kind"] != "lib", b["target"]))
    return binaries


def package_name(package_id, manifest_dir):
    # "path+file:///work/main/tests#dsrl-e2e@0.1.0" or the older "dsrl-e2e 0.1.0 (path+file://...)".
    if "#" in package_id:
        tail = package_id.rsplit("#", 1)[1]
        name = tail.split("@", 1)[0]
        return name if "@" in tail else os.path.basename(manifest_dir)
    return package_id.split(" ", 1)[0]


def package_version(package_id):
    if "#" in package_id:
        tail = package_id.rsplit("#", 1)[1]
        return tail.split("@", 1)[1] if "@" in tail else tail
    return package_id.split(" ")[1]


def environment(binary, cargo):
    env = dict(os.environ)
    env.update({
        "CARGO": cargo,
        "CARGO_MANIFEST_DIR": binary["manifest_dir"],
        "CARGO_PKG_NAME": binary["package"],
        "CARGO_PKG_VERSION": binary["version"],
        "CARGO_CRATE_NAME": binary["target"].replace("-", "_"),
    })
    return env


def header(binary):
    what = "unittests " if binary["kind"] in ("lib", "cdylib", "bin") else ""
    return f"     Running {what}{binary['src']} ({binary['executable']})\n"


def run(binary, cargo, stream):
    """Runs one test binary; returns whether it passed."""
    command = [binary["executable"]]
    if stream:
        with printing:
            sys.stdout.write(header(binary))
            sys.stdout.flush()
        process = subprocess.Popen(command, cwd=binary["manifest_dir"], env=environment(binary, cargo),
                                   stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True, bufsize=1)
        for line in process.stdout:
            with printing:
                sys.stdout.write(line)
                sys.stdout.flush()
        return process.wait() == 0
    done = subprocess.run(command, cwd=binary["manifest_dir"], env=environment(binary, cargo),
                          stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
    with printing:
        sys.stdout.write(header(binary) + done.stdout)
        sys.stdout.flush()
    return done.returncode == 0


def main():
    options = sys.argv[1:]
    cargo = os.environ.get("CARGO") or shutil.which("cargo")
    binaries = test_binaries(cargo, options)
    e2e = [b for b in binaries if b["package"] == E2E_PACKAGE and b["target"] == E2E_TARGET]
    others = [b for b in binaries if b not in e2e]
    failed = []

    def lane(members, stream):
        for binary in members:
            if not run(binary, cargo, stream):
                failed.append(f"{binary['package']} ({binary['src']})")

    threads = [threading.Thread(target=lane, args=(e2e, True)),
               threading.Thread(target=lane, args=(others, False))]
    for thread in threads:
        thread.start()
    for thread in threads:
        thread.join()
    doc = subprocess.run([cargo, "test", *options, "--workspace", "--doc", "--no-fail-fast"])
    if doc.returncode != 0:
        failed.append("doc-tests")
    if failed:
        print(f"failed: {', '.join(failed)}", file=sys.stderr)
        sys.exit(1)


if __name__ == "__main__":
    main()
