#!/bin/sh
# Checks the systemd integration files without a running systemd and without relightd installed:
#   - relightd.service with `systemd-analyze verify` (ExecStart=/ExecReload= pointed at an existing
#     binary in a temporary copy); any message that mentions the unit fails the check;
#   - its sandbox with `systemd-analyze security --offline=yes`: the exposure must be 2.0 or less;
#   - sysusers.d/ and tmpfiles.d/ by applying them to a scratch root directory;
#   - the udev rules with `udevadm verify` where this systemd has it (v254+).
# Usage: systemd/verify.sh   (exit status 0 when everything is clean)
set -eu

here=$(cd "$(dirname "$0")" && pwd)
scratch=$(mktemp -d)
trap 'rm -rf "$scratch"' EXIT INT TERM
failed=0

stand_in=$(command -v true)
mkdir -p "$scratch/units"
sed -e "s|/usr/bin/relightd|$stand_in|g" -e "s|/usr/bin/relightctl|$stand_in|g" \
    "$here/relightd.service" >"$scratch/units/relightd.service"

echo "== systemd-analyze verify relightd.service"
status=0
# At level info a clean unit produces no output; unknown keys and unparsable values are only
# logged ("..., ignoring.") and do not change the exit status, so any line naming the unit fails.
SYSTEMD_LOG_LEVEL=info SYSTEMD_LOG_COLOR=0 \
    systemd-analyze verify --man=no "$scratch/units/relightd.service" \
    >"$scratch/verify.log" 2>&1 || status=$?
if grep 'relightd\.service' "$scratch/verify.log"; then
    failed=1
fi
if [ "$status" -ne 0 ]; then
    echo "systemd-analyze verify exited with $status:"
    cat "$scratch/verify.log"
    failed=1
fi

echo "== systemd-analyze security relightd.service (exposure at most 2.0)"
# Offline: the unit file's own settings are scored, not a running service's. Needs systemd 250+.
if systemd-analyze security --help 2>/dev/null | grep -q -- '--offline'; then
    SYSTEMD_LOG_COLOR=0 systemd-analyze security --offline=yes --no-pager \
        "$scratch/units/relightd.service" >"$scratch/security.log" 2>&1 || true
    exposure=$(sed -n 's/.*Overall exposure level for relightd\.service: \([0-9.]*\).*/\1/p' \
        "$scratch/security.log")
    if [ -z "$exposure" ]; then
        echo "no exposure level in the output:"
        cat "$scratch/security.log"
        failed=1
    elif awk -v e="$exposure" 'BEGIN { exit !(e > 2.0) }'; then
        echo "exposure $exposure is above 2.0:"
        grep '✗' "$scratch/security.log"
        failed=1
    else
        echo "exposure $exposure"
    fi
else
    echo "(systemd-analyze security --offline needs systemd 250+; not checked)"
fi

echo "== sysusers.d/relightd.conf"
mkdir -p "$scratch/root/etc"
if ! systemd-sysusers --root="$scratch/root" "$here/sysusers.d/relightd.conf"; then
    failed=1
elif ! grep -q '^relightd:' "$scratch/root/etc/passwd"; then
    echo "sysusers.d/relightd.conf did not create user relightd"
    failed=1
fi

echo "== tmpfiles.d/relightd.conf"
if ! systemd-tmpfiles --root="$scratch/root" --create "$here/tmpfiles.d/relightd.conf"; then
    failed=1
elif [ ! -d "$scratch/root/var/lib/relightd/recordings" ]; then
    echo "tmpfiles.d/relightd.conf did not create /var/lib/relightd/recordings"
    failed=1
fi

echo "== udev/70-relight.rules"
if udevadm verify --help >/dev/null 2>&1; then
    udevadm verify "$here/udev/70-relight.rules" || failed=1
else
    echo "(udevadm verify needs systemd 254+; checking that every line is a comment, label or rule)"
    if grep -nEv '^[[:space:]]*(#.*)?$|^(SUBSYSTEM|ENV|ATTR|LABEL)' "$here/udev/70-relight.rules"; then
        echo "unexpected lines above"
        failed=1
    fi
fi

if [ "$failed" -ne 0 ]; then
    echo "systemd/verify.sh: FAILED"
    exit 1
fi
echo "systemd/verify.sh: ok"
