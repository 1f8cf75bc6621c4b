#!/usr/bin/env bash
# Three hospitals and a coordinator on one Linux machine, with network namespaces.
#
#   sudo deploy/three-hospitals.sh [--seconds S] [--presets "P1 P2 P3"] [--bin DIR] [--keep DIR]
#
# Needs root (ip netns), iproute2, and the binaries (built with `cargo build --release` if
# --bin is not given). Topology (all addresses exist only inside the namespaces; the host's
# own interfaces, addresses and routes are never touched):
#
#   netns cosurg-coord-PID                     netns cosurg-hospN-PID (N = 1, 2, 3)
#   cosurg-server --listen 0.0.0.0:4433        cosurg join --server 127.0.0.1:4433 ...
#     veth cN 10.77.0.(4N-3)/30  <---------->    veth hN 10.77.0.(4N-2)/30
#                                              cosurg netem --listen 127.0.0.1:4433
#                                                --upstream 10.77.0.(4N-3):4433 --preset PN
#
# Each hospital reaches the coordinator over its own veth link; `cosurg netem` inside the
# hospital namespace impairs that hospital's access link in user space (this kernel has no
# tc netem). The coordinator sees three distinct hosts on UDP 4433, as on real machines.
# Every site runs `cosurg join` for --seconds simulated seconds and prints its JSON summary;
# the script prints the three summaries and the coordinator's final counters. On exit
# (normal, error or Ctrl-C) it stops what it started and deletes its namespaces (trap).
set -euo pipefail

here="$(cd "$(dirname "${BASH_SOURCE[0]}")" && pwd)"
repo="$(cd "$here/.." && pwd)"

seconds=12
presets="metro average intercontinental"
bin=""
keep=""
session="three-hospitals"
token="${COSURG_TOKEN:-tok-$RANDOM$RANDOM}"
join_extra=()

usage() { sed -n '2,20p' "$0" | sed 's/^# \{0,1\}//'; }
while [[ $# -gt 0 ]]; do
    case "$1" in
        --seconds) seconds="$2"; shift 2 ;;
        --presets) presets="$2"; shift 2 ;;
        --bin) bin="$2"; shift 2 ;;
        --keep) keep="$2"; shift 2 ;;
        --) shift; join_extra=("$@"); break ;;   # extra `cosurg join` flags for every site
        -h|--help) usage; exit 0 ;;
        *) echo "unknown argument $1" >&2; usage >&2; exit 2 ;;
    esac
done
read -r -a preset_of <<<"$presets"
[[ ${#preset_of[@]} -eq 3 ]] || { echo "--presets needs three names" >&2; exit 2; }

if [[ $EUID -ne 0 ]]; then
    echo "needs root for ip netns (try: sudo $0 $*)" >&2
    exit 2
fi
command -v ip >/dev/null || { echo "needs iproute2 (ip)" >&2; exit 2; }

if [[ -z "$bin" ]]; then
    echo "== building cosurg and cosurg-server (release)"
    (cd "$repo" && cargo build --release --bin cosurg --bin cosurg-server)
    bin="${CARGO_TARGET_DIR:-$repo/target}/release"
fi
bin="$(cd "$bin" && pwd)"
for b in cosurg cosurg-server; do
    [[ -x "$bin/$b" ]] || { echo "missing binary $bin/$b" >&2; exit 2; }
done

tag="$$"
coord="cosurg-coord-$tag"
hosp=("cosurg-hosp1-$tag" "cosurg-hosp2-$tag" "cosurg-hosp3-$tag")
names=(hospital-a hospital-b hospital-c)
roles=(instructor trainee trainee)
tools=(forceps forceps probe)
starts=(0.5 7.0 1.0)
work="$(mktemp -d "${TMPDIR:-/tmp}/cosurg-3h.XXXXXX")"
pids=()
made_ns=()

cleanup() {
    local rc=$?
    trap - EXIT INT TERM
    for p in "${pids[@]}"; do kill "$p" 2>/dev/null || true; done
    for p in "${pids[@]}"; do wait "$p" 2>/dev/null || true; done
    for ns in "${made_ns[@]}"; do ip netns del "$ns" 2>/dev/null || true; done
    if [[ -n "$keep" ]]; then
        mkdir -p "$keep" && cp -r "$work"/. "$keep"/ && echo "logs kept in $keep"
    fi
    rm -rf "$work"
    exit "$rc"
}
trap cleanup EXIT
trap 'exit 130' INT TERM

# Foreground helper only: background processes are started with `ip netns exec … &`
# directly, so that $! is the process itself (it execs) and signals reach it.
in_ns() { local ns="$1"; shift; ip netns exec "$ns" "$@"; }

# wait_line FILE REGEX [TRIES]: print the first match of REGEX in FILE (0.1 s per try).
wait_line() {
    local tries="${3:-300}"
    for _ in $(seq "$tries"); do
        if v="$(grep -oP "$2" "$1" 2>/dev/null | head -1)" && [[ -n "$v" ]]; then
            echo "$v"; return 0
        fi
        sleep 0.1
    done
    echo "timed out waiting for /$2/ in $1" >&2
    return 1
}

echo "== namespaces and links (10.77.0.0/24, inside the namespaces only)"
ip netns add "$coord"; made_ns+=("$coord")
in_ns "$coord" ip link set lo up
for i in 0 1 2; do
    n=$((i + 1))
    ns="${hosp[$i]}"
    ip netns add "$ns"; made_ns+=("$ns")
    in_ns "$ns" ip link set lo up
    # Created inside the coordinator namespace with its peer placed directly in the
    # hospital namespace: the veth pair never exists in the host's namespace.
    ip -n "$coord" link add "c$n" type veth peer name "h$n" netns "$ns"
    ip -n "$coord" addr add "10.77.0.$((4 * n - 3))/30" dev "c$n"
    ip -n "$ns" addr add "10.77.0.$((4 * n - 2))/30" dev "h$n"
    ip -n "$coord" link set "c$n" up
    ip -n "$ns" link set "h$n" up
    echo "  ${names[$i]}: $ns 10.77.0.$((4 * n - 2)) <-> $coord 10.77.0.$((4 * n - 3)), netem preset ${preset_of[$i]}"
done

limit=$(awk -v s="$seconds" 'BEGIN { printf "%d", s * 8 + 90 }')

echo "== coordinator (netns $coord)"
ip netns exec "$coord" env RUST_LOG=info "$bin/cosurg-server" --listen 0.0.0.0:4433 \
    --session "$session" --token "$token" --state-dir "$work/state" --seconds "$limit" \
    --status-interval 2 >"$work/coordinator.out" 2>"$work/coordinator.log" &
server_pid=$!
pids+=("$server_pid")
fp="$(wait_line "$work/coordinator.out" 'fingerprint: \K\S+')"
wait_line "$work/coordinator.out" 'listening: \K\S+' >/dev/null
echo "  listening on 0.0.0.0:4433, fingerprint $fp"

echo "== impaired access links (cosurg netem in each hospital)"
for i in 0 1 2; do
    n=$((i + 1))
    ip netns exec "${hosp[$i]}" "$bin/cosurg" netem --listen 127.0.0.1:4433 \
        --upstream "10.77.0.$((4 * n - 3)):4433" --preset "${preset_of[$i]}" --seed "$n" \
        --seconds "$limit" >"$work/netem-$n.out" 2>"$work/netem-$n.log" &
    pids+=($!)
    wait_line "$work/netem-$n.out" 'netem listening: \K\S+' >/dev/null
done

echo "== sites (cosurg join, $seconds simulated seconds each)"
site_pids=()
for i in 0 1 2; do
    n=$((i + 1))
    # The instructor joins with the token; the others with an invitation bound to their name.
    if [[ "${roles[$i]}" == instructor ]]; then
        credential=(--token "$token")
    else
        credential=(--invite "$("$bin/cosurg-server" invite --role "${roles[$i]}" \
            --site "${names[$i]}" --expires 2h --state-dir "$work/state")")
    fi
    ip netns exec "${hosp[$i]}" timeout "$limit" "$bin/cosurg" join \
        --server 127.0.0.1:4433 --session "$session" "${credential[@]}" \
        --role "${roles[$i]}" --site "${names[$i]}" --pin "$fp" \
        --tool "${tools[$i]}" --script-start "${starts[$i]}" \
        --seconds "$seconds" --expect-sites 3 --seed "$n" \
        --out "$work/${names[$i]}" --json "${join_extra[@]}" \
        >"$work/${names[$i]}.json" 2>"$work/${names[$i]}.log" &
    site_pids+=($!)
    pids+=($!)
done

failed=0
for i in 0 1 2; do
    if wait "${site_pids[$i]}"; then
        echo "  ${names[$i]}: done"
    else
        rc=$?
        echo "  ${names[$i]}: FAILED (exit $rc); log:"
        sed 's/^/    /' "$work/${names[$i]}.log" | tail -20
        failed=1
    fi
done

# Stop the relays and the coordinator with SIGINT so they print their counters.
for p in "${pids[@]}"; do
    kill -INT "$p" 2>/dev/null || true
done
for p in "${pids[@]}"; do wait "$p" 2>/dev/null || true; done
pids=()

echo
echo "== site summaries (JSON)"
for i in 0 1 2; do
    echo "-- ${names[$i]} (${roles[$i]}, ${preset_of[$i]})"
    cat "$work/${names[$i]}.json"
done
echo
echo "== netem counters"
for i in 0 1 2; do
    echo "-- ${names[$i]} (${preset_of[$i]})"
    grep -v '^netem \(listening\|upstream\)' "$work/netem-$((i + 1)).out" || true
done
echo
echo "== coordinator"
grep -E 'site joined|site left|refused|timed out' "$work/coordinator.log" \
    | sed -E 's/^[0-9T:.-]+Z +//' || true
grep '^stopped:' "$work/coordinator.out" || true

for i in 0 1 2; do
    grep -q '^{' "$work/${names[$i]}.json" || { echo "no JSON summary from ${names[$i]}"; failed=1; }
done
if [[ $failed -ne 0 ]]; then
    echo "three-hospitals: FAIL"
    exit 1
fi
echo "three-hospitals: PASS"
