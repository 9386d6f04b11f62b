#!/bin/sh
# Runs volfxd as deploy/volfxd.service would, without systemd: the unit's main file-system and
# privilege settings rebuilt with unshare and setpriv, so that a test can check that volfxd,
# PoCL's kernel compiler included, works under them. Needs root (it mounts); prints
# "volfxd listening on ..." like volfxd and ends with volfxd's exit status.
#
#   service_sandbox.sh VOLFXD CONFIG SCENES_DIR [volfxd options...]
#
# VOLFXD is installed as /usr/local/bin/volfxd, CONFIG as /usr/local/etc/volfx/volfxd.json and
# SCENES_DIR as /usr/local/share/volfx/scenes (the paths deploy/volfxd.example.json names) on a
# private /usr/local; the unit's settings are approximated as follows:
#   ProtectSystem=strict     every mount remounted read-only
#   RuntimeDirectory=volfx   /run/volfx on a private /run, owned by the service user
#   StateDirectory=volfx     /var/lib/volfx on a private /var/lib
#   CacheDirectory=volfx     /var/cache/volfx on a private /var/cache, PoCL's cache empty
#   PrivateTmp=yes           a private /tmp
#   ProtectHome=yes          empty read-only /home and /root
#   PrivateDevices=yes       a /dev holding null, zero, full, random, urandom and tty only
#   ProtectProc=invisible    a /proc showing other users' processes to nobody
#   ProtectKernelTunables=yes, ProtectControlGroups=yes   /sys read-only
#   User=volfx               uid and gid 65534, no supplementary groups
#   NoNewPrivileges=yes, CapabilityBoundingSet= , UMask=0007
#   MemoryDenyWriteExecute=yes   the kernel's own (prctl PR_SET_MDWE, Linux 6.3 and later;
#                            skipped on older kernels), which refuses the same mappings
# The system call filter, address families, namespaces and PrivateUsers= are not rebuilt here:
# only systemd applies them.
set -eu
[ $# -ge 3 ] || { echo "usage: $0 VOLFXD CONFIG SCENES_DIR [volfxd options...]" >&2; exit 2; }
volfxd=$(readlink -f "$1") config=$(readlink -f "$2") scenes=$(readlink -f "$3")
shift 3
export SANDBOX_VOLFXD="$volfxd" SANDBOX_CONFIG="$config" SANDBOX_SCENES="$scenes"

exec unshare --mount --pid --ipc --uts --fork --kill-child --propagation private sh -eu -c '
uid=65534 gid=65534
# ProtectSystem=strict (and /sys for ProtectKernelTunables=, ProtectControlGroups=). Deepest
# mounts first; /proc and /dev are replaced below.
awk "{print \$5}" /proc/self/mountinfo | sort -r | while read -r mp; do
  case "$mp" in /proc|/proc/*|/dev|/dev/*) continue ;; esac
  mount -o remount,bind,ro "$mp" 2>/dev/null || true
done

# The installed files, on a private read-only /usr/local.
mount -t tmpfs -o mode=0755 tmpfs /usr/local
mkdir -p /usr/local/bin /usr/local/etc/volfx /usr/local/share/volfx
cp "$SANDBOX_VOLFXD" /usr/local/bin/volfxd
cp "$SANDBOX_CONFIG" /usr/local/etc/volfx/volfxd.json
cp -r "$SANDBOX_SCENES" /usr/local/share/volfx/scenes
# A sanitizer build'"'"'s leak suppressions, which may lie under a directory hidden below.
supp= opts=
IFS=:
for o in ${LSAN_OPTIONS:-}; do
  case "$o" in
    suppressions=*) supp=${o#suppressions=} o=suppressions=/usr/local/etc/volfx/lsan.supp ;;
  esac
  opts=${opts:+$opts:}$o
done
unset IFS
if [ -n "$supp" ] && [ -r "$supp" ]; then
  cp "$supp" /usr/local/etc/volfx/lsan.supp
  LSAN_OPTIONS=$opts
fi
mount -o remount,ro /usr/local

# RuntimeDirectory=, StateDirectory=, CacheDirectory= (mode 0750, owned by the user), PrivateTmp=.
for d in /run /var/lib /var/cache; do
  mount -t tmpfs -o mode=0755,nosuid,nodev tmpfs "$d"
  install -d -m 0750 -o $uid -g $gid "$d/volfx"
done
mount -t tmpfs -o mode=1777,nosuid,nodev tmpfs /tmp

# ProtectHome=yes.
for d in /home /root; do
  [ -d "$d" ] && mount -t tmpfs -o ro,mode=0755 tmpfs "$d"
done

# PrivateDevices=yes.
mount -t tmpfs -o mode=0755,nosuid,noexec tmpfs /dev
mknod -m 0666 /dev/null c 1 3
mknod -m 0666 /dev/zero c 1 5
mknod -m 0666 /dev/full c 1 7
mknod -m 0666 /dev/random c 1 8
mknod -m 0666 /dev/urandom c 1 9
mknod -m 0666 /dev/tty c 5 0
mkdir -m 1777 /dev/shm

# ProtectProc=invisible.
mount -t proc -o nosuid,nodev,noexec,hidepid=invisible proc /proc

# MemoryDenyWriteExecute=yes, then exec: PR_SET_MDWE (65) with PR_MDWE_REFUSE_EXEC_GAIN (1).
mdwe="import ctypes, os, sys
if ctypes.CDLL(None, use_errno=True).prctl(65, 1, 0, 0, 0) != 0:
    print(\"volfxd-sandbox: no PR_SET_MDWE in this kernel\", file=sys.stderr)
os.execv(sys.argv[1], sys.argv[1:])"

umask 0007
exec setpriv --reuid=$uid --regid=$gid --clear-groups --no-new-privs --inh-caps=-all \
  --bounding-set=-all -- env -i PATH=/usr/local/bin:/usr/bin:/bin HOME=/var/lib/volfx \
  POCL_CACHE_DIR=/var/cache/volfx/pocl ${ASAN_OPTIONS:+ASAN_OPTIONS="$ASAN_OPTIONS"} \
  ${UBSAN_OPTIONS:+UBSAN_OPTIONS="$UBSAN_OPTIONS"} ${LSAN_OPTIONS:+LSAN_OPTIONS="$LSAN_OPTIONS"} \
  python3 -c "$mdwe" /usr/local/bin/volfxd --config /usr/local/etc/volfx/volfxd.json "$@"
' volfxd-sandbox "$@"
