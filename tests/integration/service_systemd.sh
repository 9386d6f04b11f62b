#!/bin/sh
# Boots systemd as PID 1 of private namespaces, with deploy/volfxd.service installed as the
# install steps at the top of the unit say, so that a test can start volfxd under the real unit
# (every sandboxing setting, the system call filter included) on a machine whose PID 1 is not
# systemd. Needs root, cgroup2 and overlayfs; the host's files stay as they are: /etc and /var
# are overlays whose changes go to WORK, and /run, /tmp and /usr/local are private.
#
#   service_systemd.sh WORK VOLFXD CONFIG SCENES [DROPIN]
#
# WORK is an empty directory for the overlays; VOLFXD, CONFIG and SCENES are installed as
# /usr/local/bin/volfxd, /etc/volfx/volfxd.json and /usr/local/share/volfx/scenes; DROPIN, if
# given, as /etc/systemd/system/volfxd.service.d/test.conf. systemd starts volfx-test.target,
# which wants journald and volfxd. The caller talks to it with
# `nsenter -t PID -m -p systemctl ...`, PID being this process's child, and ends it with
# SIGKILL to that child; it then removes WORK and the cgroup named in WORK/cgroup.
set -eu
[ $# -ge 4 ] || { echo "usage: $0 WORK VOLFXD CONFIG SCENES [DROPIN]" >&2; exit 2; }
here=$(cd "$(dirname "$0")" && pwd)
unit=$here/../../deploy/volfxd.service
sysusers=$here/../../deploy/volfx.sysusers.conf
work=$(readlink -f "$1")
export SD_WORK="$work" SD_VOLFXD="$(readlink -f "$2")" SD_CONFIG="$(readlink -f "$3")" \
  SD_SCENES="$(readlink -f "$4")" SD_DROPIN="${5:+$(readlink -f "$5")}" SD_UNIT="$unit" \
  SD_SYSUSERS="$sysusers"

# A cgroup of our own under the current one, which becomes the root of systemd's cgroup
# namespace.
cg2=$(awk '$9 == "cgroup2" {print $5; exit}' /proc/self/mountinfo)
[ -n "$cg2" ] || { echo "no cgroup2 mount" >&2; exit 3; }
cur=$(sed -n 's/^0:://p' /proc/self/cgroup)
cg=$cg2${cur%/}/volfx-systemd-$$
mkdir "$cg"
echo "$cg" >"$work/cgroup"
echo $$ >"$cg/cgroup.procs"

exec unshare --mount --pid --fork --kill-child --cgroup --uts --ipc --propagation private sh -eu -c '
mkdir -p "$SD_WORK/etc" "$SD_WORK/etc.work" "$SD_WORK/var" "$SD_WORK/var.work"
mount -t overlay overlay -o "lowerdir=/etc,upperdir=$SD_WORK/etc,workdir=$SD_WORK/etc.work" /etc
mount -t overlay overlay -o "lowerdir=/var,upperdir=$SD_WORK/var,workdir=$SD_WORK/var.work" /var
mount -t tmpfs tmpfs /run
mount -t tmpfs -o mode=0755 tmpfs /usr/local
mkdir -p /usr/local/bin /usr/local/share/volfx /etc/volfx /etc/sysusers.d
cp "$SD_VOLFXD" /usr/local/bin/volfxd
cp -r "$SD_SCENES" /usr/local/share/volfx/scenes
cp "$SD_CONFIG" /etc/volfx/volfxd.json
cp "$SD_SYSUSERS" /etc/sysusers.d/volfx.conf
systemd-sysusers /etc/sysusers.d/volfx.conf
cp "$SD_UNIT" /etc/systemd/system/volfxd.service
if [ -n "$SD_DROPIN" ]; then
  mkdir -p /etc/systemd/system/volfxd.service.d
  cp "$SD_DROPIN" /etc/systemd/system/volfxd.service.d/test.conf
fi
printf "[Unit]\nDescription=volfx test\nWants=systemd-journald.service volfxd.service\n" \
  >/etc/systemd/system/volfx-test.target
echo volfx-test >/etc/hostname
# Last, since the files copied above may have been in /tmp.
mount -t tmpfs tmpfs /tmp
mount -t cgroup2 cgroup2 /sys/fs/cgroup
mount -t proc proc /proc
exec env -i container=volfx-test PATH=/usr/sbin:/usr/bin:/sbin:/bin \
  /lib/systemd/systemd --unit=volfx-test.target
'
