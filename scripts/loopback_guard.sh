#!/usr/bin/env bash
# Run a command while capturing UDP on every interface except loopback; fail if any DDS
# (RTPS) packet, or any UDP packet from the domain's DDS ports, left the host's loopback.
# Needs root and tcpdump; without them it says so and just runs the command.
set -uo pipefail
if ! command -v tcpdump >/dev/null || [ "$(id -u)" != 0 ]; then
  echo "loopback_guard: tcpdump/root unavailable, running without the capture" >&2
  exec "$@"
fi
cap=$(mktemp -d)
# RTPS magic at the start of the UDP payload (IPv4), any UDP over IPv6 except ::1.
filter='(ip and udp and not net 127.0.0.0/8 and udp[8:4] = 0x52545053) or (ip and udp and not net 127.0.0.0/8 and portrange 7400-32767 and not port 53) or (ip6 and udp and not host ::1 and not port 53 and not port 547 and not port 546)'
tcpdump -i any -nn -U -w "$cap/leak.pcap" "$filter" >"$cap/tcpdump.log" 2>&1 &
tpid=$!
sleep 1
"$@"
code=$?
sleep 1
kill "$tpid" 2>/dev/null; wait "$tpid" 2>/dev/null
leaked=$(tcpdump -nn -r "$cap/leak.pcap" 2>/dev/null | wc -l)
if [ "$leaked" -gt 0 ]; then
  echo "loopback_guard: $leaked UDP packet(s) left loopback:" >&2
  tcpdump -nn -r "$cap/leak.pcap" 2>/dev/null | head -20 >&2
  code=3  # a leak outranks the command's own failure (callers tolerate some of those)
else
  echo "loopback_guard: 0 DDS/UDP packets outside loopback while the command ran" >&2
fi
rm -rf "$cap"
exit "$code"
