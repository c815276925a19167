#!/usr/bin/env bash
# Makes sure /dev/null is the null device. Some sandboxes start without one; the first `> /dev/null` then creates
# a regular file, every program that discards output writes into it, and every program that reads it (cargo
# hands it to rustc as standard input) gets that text back. Seen on this project's build machines.
set -euo pipefail
if [ -c /dev/null ]; then
  exit 0
fi
if [ "$(id -u)" -ne 0 ]; then
  echo "/dev/null is not the null device; as root run: rm -f /dev/null && mknod -m 666 /dev/null c 1 3" >&2
  exit 1
fi
rm -f /dev/null
mknod -m 666 /dev/null c 1 3
echo "repaired /dev/null (it was not a character device)" >&2
