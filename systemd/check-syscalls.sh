#!/bin/sh
# Runs relightd under strace the way the service runs it (replaying the bundled recording into
# a GPU engine, with composites, a snapshot, a recording, an engine switch and a reload, then
# SIGTERM) and checks that every system call it made passes relightd.service's
# SystemCallFilter= lines. A call outside the filter would fail with EPERM under systemd
# (SystemCallErrorNumber=EPERM), which shows up as an odd I/O error, not as a clear crash.
#
# What this cannot see: the hardware backends' vendor libraries (OpenNI2, libfreenect, uEye,
# V4L2, libusb hot-plug) and a vendor GPU driver; run it on the rig with a device config to
# check those (CONFIG below).
#
# Usage: systemd/check-syscalls.sh [BIN_DIR [CONFIG]]   (BIN_DIR: where relightd and relightctl
#        are, default target/debug; CONFIG: a config to run instead of the built-in replay one)
set -eu

here=$(cd "$(dirname "$0")" && pwd)
root=$(dirname "$here")
bin=${1:-$root/target/debug}
command -v strace >/dev/null || { echo "check-syscalls: needs strace (apt-get install strace)"; exit 1; }
# A container without ptrace rights cannot trace at all: say so and skip, rather than fail on
# the machine instead of the daemon.
if ! strace -f -qq -o /dev/null true 2>/dev/null; then
    echo "check-syscalls: strace cannot trace here (ptrace not permitted); NOT CHECKED"
    exit 0
fi
scratch=$(mktemp -d)
trap 'rm -rf "$scratch"' EXIT INT TERM

config=${2:-}
if [ -z "$config" ]; then
    config=$scratch/relightd.toml
    mkdir -p "$scratch/recordings" "$scratch/snapshots" "$scratch/out"
    cat >"$config" <<TOML
[daemon]
socket = "$scratch/control.sock"
watchdog = false

[replay]
path = "$root/tests/fixtures/demo.mcap"
loop = true

[scene]
dir = "$root/tests/scenes/desk_box"
depth_stride = 4

[engine]
name = "differential"

[engine.params]
rsm_size = 128

[recorder]
dir = "$scratch/recordings"

[snapshot]
dir = "$scratch/snapshots"

[output]
dir = "$scratch/out"
every_n = 5
TOML
fi
socket=$(sed -n 's/^socket *= *"\(.*\)"/\1/p' "$config" | head -n 1)

strace -f -qq -c -o "$scratch/summary" "$bin/relightd" --config "$config" run \
    >"$scratch/relightd.log" 2>&1 &
tracer=$!
ctl() { "$bin/relightctl" --socket "$socket" "$@" >/dev/null; }
waited=0
until ctl status 2>/dev/null; do
    waited=$((waited + 1))
    if [ "$waited" -gt 120 ]; then
        echo "check-syscalls: relightd never served $socket:"
        cat "$scratch/relightd.log"
        exit 1
    fi
    sleep 0.5
done
sleep 5
ctl snapshot
ctl record start check.mcap
sleep 3
ctl record stop
ctl engine set dvct
sleep 5
ctl reload
sleep 1
kill -TERM "$(pgrep -P "$tracer" -x relightd)"
wait "$tracer" || { echo "check-syscalls: relightd failed:"; cat "$scratch/relightd.log"; exit 1; }

# Every call strace counted, against the unit's filter expanded by this systemd's own groups.
systemd-analyze syscall-filter --no-pager >"$scratch/groups" 2>/dev/null
grep '^SystemCallFilter=' "$here/relightd.service" | cut -d= -f2- >"$scratch/filter"
python3 - "$scratch/summary" "$scratch/groups" "$scratch/filter" <<'PY'
import sys

summary, groups_file, filter_file = sys.argv[1:]
groups, current = {}, None
for line in open(groups_file):
    text = line.strip()
    if not text or text.startswith("#"):
        continue
    if not line[0].isspace():
        current = groups.setdefault(text, [])
    elif current is not None:
        current.append(text)

def expand(name):
    if not name.startswith("@"):
        return {name}
    return set().union(*(expand(n) for n in groups[name]))

allowed = set()
for line in open(filter_file):
    # As systemd reads it: a leading "~" makes the whole line a deny list.
    deny = line.startswith("~")
    names = set().union(*(expand(word) for word in line.lstrip("~").split()))
    if deny:
        allowed -= names
    else:
        allowed |= names

used = set()
for line in open(summary):
    fields = line.split()
    if len(fields) >= 5 and fields[0][0].isdigit() and fields[-1] != "total":
        used.add(fields[-1])
outside = sorted(used - allowed)
print(f"{len(used)} system calls used, {len(allowed)} allowed by relightd.service")
if outside:
    print("outside SystemCallFilter=:", " ".join(outside))
    sys.exit(1)
PY
echo "systemd/check-syscalls.sh: ok"
