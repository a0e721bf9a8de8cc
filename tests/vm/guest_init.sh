#!/bin/busybox sh
# PID 1 of the throwaway guest (see tests/vm/netem_vm.py). It runs from the initramfs that
# netem_vm builds: busybox + the Debian kernel modules listed in /modules.order.
#
# Loads the modules (9p/virtio to reach the host, qdiscs/veth/ifb for the tests), mounts the
# host's root read-only over 9p at /newroot with private tmpfs for everything a test writes,
# mounts the writable 9p share `out` at /run/vmout and the checkout's own read-only share at
# its host path (listed in /run/vmout/binds), runs /run/vmout/job.sh chrooted into the host's
# root, and powers off. The job's exit status goes to /run/vmout/rc and to the console
# as "EDGELOC-VM-EXIT <rc>": the host trusts only that, so a guest that dies early fails.
/bin/busybox mkdir -p /bin /sbin /proc /sys /dev /newroot
/bin/busybox --install -s /bin
export PATH=/bin

fail() {
    echo "EDGELOC-VM-FAIL $*"
    poweroff -f
    sleep 5
}

mount -t proc proc /proc
mount -t sysfs sysfs /sys
mount -t devtmpfs devtmpfs /dev
echo "EDGELOC-VM-BOOTED $(cut -d' ' -f1 /proc/uptime)"

# modules.order: one path per line, dependencies before the modules that need them.
while read -r ko; do
    insmod "/$ko" || fail "insmod $ko"
done < /modules.order

# 9p over virtio; the page cache is safe (cache=loose) because the host side is read-only
# for the guest and nothing on the host changes what the tests read while they run.
opts=trans=virtio,version=9p2000.L,msize=512000
mount -t 9p -o "$opts,ro,cache=loose" hostroot /newroot || fail "mount the host root over 9p"
for d in proc sys dev; do
    mount --move "/$d" "/newroot/$d" || fail "move /$d"
done
# The host's read-only tree has mountpoints for all of these; each gets the guest's own.
mount -t tmpfs -o mode=1777 tmpfs /newroot/tmp || fail "tmpfs /tmp"
mount -t tmpfs -o mode=1777 tmpfs /newroot/var/tmp || fail "tmpfs /var/tmp"
mount -t tmpfs -o mode=0755 tmpfs /newroot/run || fail "tmpfs /run"
mkdir -p /newroot/dev/shm /newroot/dev/pts
mount -t tmpfs -o mode=1777 tmpfs /newroot/dev/shm || fail "tmpfs /dev/shm"
mount -t devpts devpts /newroot/dev/pts || fail "devpts"
mount -t cgroup2 cgroup2 /newroot/sys/fs/cgroup 2>/dev/null || true
mkdir -p /newroot/run/vmout /newroot/run/netns
mount -t 9p -o "$opts,rw" out /newroot/run/vmout || fail "mount the output share over 9p"
# The checkout (and an outside venv) at their host paths, exported on their own: last, so a
# checkout under /tmp or /run lands on the tmpfs above instead of being hidden by it.
i=0
while IFS= read -r dir; do
    mkdir -p "/newroot$dir" || fail "mkdir $dir"
    mount -t 9p -o "$opts,ro,cache=loose" "bind$i" "/newroot$dir" || fail "mount $dir over 9p"
    i=$((i + 1))
done < /newroot/run/vmout/binds
echo "EDGELOC-VM-READY $(cut -d' ' -f1 /newroot/proc/uptime)"

chroot /newroot /bin/sh /run/vmout/job.sh
rc=$?
echo "$rc" > /newroot/run/vmout/rc
sync
echo "EDGELOC-VM-EXIT $rc"
poweroff -f
sleep 5
