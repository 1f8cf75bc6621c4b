#!/usr/bin/env bash
# Interop check: a Python aioquic client against cosurg-server, through `cosurg netem`.
#
#   deploy/interop/run.sh            # build (release), run, check; exit 0 on success
#   PRESET=poor deploy/interop/run.sh
#   COSURG_BIN_DIR=target/debug deploy/interop/run.sh   # use already built binaries
#
# Starts, on 127.0.0.1 with free ports, `cosurg-server` (state dir in a temp dir, bounded by
# --seconds) and `cosurg netem` (preset $PRESET, default `average`) in front of it, then runs
# deploy/interop/aioquic_join.py through the relay in four ways:
#   garbage      pinned fingerprint, undecodable first frame -> Refusal Malformed, app close 8
#   wrong-token  pinned fingerprint, hand-encoded Join       -> Refusal WrongToken, app close 1
#   wrong-token  CA = the coordinator's PEM (server name localhost), same expectation
#   join         pinned fingerprint, correct Join            -> Welcome, datagrams both ways,
#                                                               Leave -> app close 0
# plus a wrong pin, which the client must detect before sending anything,
# and checks every run prints `RESULT: PASS`, the coordinator logged the Leave reason and the
# relay carried the traffic. Everything it started is stopped on exit (trap).
#
# Without the aioquic module it prints "skipped: aioquic not installed" and exits 0
# (INTEROP_REQUIRE=1 makes that an error). Install: pip install aioquic
set -euo pipefail

here="$(cd "$(dirname "${BASH_SOURCE[0]}")" && pwd)"
repo="$(cd "$here/../.." && pwd)"
preset="${PRESET:-average}"
python="${PYTHON:-python3}"

if ! "$python" -c "import aioquic" 2>/dev/null; then
    echo "skipped: aioquic not installed (pip install aioquic)"
    [[ "${INTEROP_REQUIRE:-0}" == 1 ]] && exit 1
    exit 0
fi

if [[ -n "${COSURG_BIN_DIR:-}" ]]; then
    bin="$(cd "$COSURG_BIN_DIR" && pwd)"
else
    echo "== building cosurg and cosurg-server (release)"
    (cd "$repo" && cargo build --release --bin cosurg --bin cosurg-server)
    bin="${CARGO_TARGET_DIR:-$repo/target}/release"
fi
for b in cosurg cosurg-server; do
    [[ -x "$bin/$b" ]] || { echo "missing binary $bin/$b"; exit 1; }
done

work="$(mktemp -d "${TMPDIR:-/tmp}/cosurg-interop.XXXXXX")"
pids=()
cleanup() {
    local rc=$?
    for p in "${pids[@]}"; do kill "$p" 2>/dev/null || true; done
    for p in "${pids[@]}"; do wait "$p" 2>/dev/null || true; done
    if [[ $rc -ne 0 ]]; then
        echo "---- coordinator log"; cat "$work/server.err" 2>/dev/null || true
        echo "---- netem output"; cat "$work/netem.out" "$work/netem.err" 2>/dev/null || true
    fi
    rm -rf "$work"
    exit $rc
}
trap cleanup EXIT INT TERM

# wait_line FILE REGEX: print the first capture of REGEX in FILE, waiting up to 15 s.
wait_line() {
    for _ in $(seq 150); do
        if v="$(grep -oP "$2" "$1" 2>/dev/null | head -1)" && [[ -n "$v" ]]; then
            echo "$v"; return 0
        fi
        sleep 0.1
    done
    echo "timed out waiting for /$2/ in $1" >&2
    return 1
}

session=interop
token=interop-token
RUST_LOG=info "$bin/cosurg-server" --listen 127.0.0.1:0 --session "$session" --token "$token" \
    --state-dir "$work/state" --seconds 120 --status-interval 0 \
    >"$work/server.out" 2>"$work/server.err" &
pids+=($!)
server_addr="$(wait_line "$work/server.out" 'listening: \K\S+')"
fp="$(wait_line "$work/server.out" 'fingerprint: \K\S+')"

"$bin/cosurg" netem --listen 127.0.0.1:0 --upstream "$server_addr" --preset "$preset" \
    --seconds 120 >"$work/netem.out" 2>"$work/netem.err" &
netem_pid=$!
pids+=("$netem_pid")
relay_addr="$(wait_line "$work/netem.out" 'netem listening: \K\S+')"
relay_port="${relay_addr##*:}"

echo "coordinator: $server_addr  fingerprint: $fp"
echo "netem:       $relay_addr -> $server_addr  preset: $preset"

failed=0
run_client() {
    local label="$1"; shift
    echo
    echo "== aioquic client: $label"
    local out="$work/client-$label.out"
    "$python" "$here/aioquic_join.py" --host 127.0.0.1 --port "$relay_port" \
        --session "$session" --token "$token" "$@" 2>&1 | tee "$out" || true
    if ! grep -q '^RESULT: PASS' "$out"; then
        echo "!! $label: no RESULT: PASS"
        failed=1
    fi
}
run_client garbage --pin "$fp" --mode garbage
run_client wrong-token --pin "$fp" --mode wrong-token
run_client wrong-token-ca --ca "$work/state/coordinator-cert.pem" --mode wrong-token
invite="$("$bin/cosurg-server" invite --role observer --site aioquic --expires 10m \
    --state-dir "$work/state")"
run_client join --pin "$fp" --mode join --invite "$invite"

# A wrong pin: the client must abort after the handshake, before sending anything.
echo
echo "== aioquic client: wrong pin (must be rejected by the client)"
"$python" "$here/aioquic_join.py" --host 127.0.0.1 --port "$relay_port" \
    --pin "$(printf '00:%.0s' {1..31})00" --mode wrong-token 2>&1 | tee "$work/client-pin.out" || true
if ! grep -q '^RESULT: FAIL certificate fingerprint does not match' "$work/client-pin.out"; then
    echo "!! wrong pin was not detected"
    failed=1
fi

echo
echo "== coordinator log"
sed -E 's/^[0-9T:.-]+Z +//' "$work/server.err"
if ! grep -q 'site left.*reason=left: aioquic interop done' "$work/server.err"; then
    echo "!! the coordinator did not log the Leave reason"
    failed=1
fi
if [[ "$(grep -c 'join refused\|bad Join' "$work/server.err")" -ne 3 ]]; then
    echo "!! expected 3 refused joins in the coordinator log"
    failed=1
fi

# Stop the relay with SIGINT so it prints its counters (Ctrl-C path).
kill -INT "$netem_pid" 2>/dev/null || true
wait "$netem_pid" 2>/dev/null || true
echo
echo "== netem counters"
cat "$work/netem.out"
if ! grep -q 'clients' "$work/netem.out"; then
    echo "!! netem printed no counters"
    failed=1
fi

echo
if [[ $failed -eq 0 ]]; then
    echo "interop: PASS (aioquic $("$python" -c 'import aioquic; print(aioquic.__version__)'), preset $preset)"
else
    echo "interop: FAIL"
    exit 1
fi
