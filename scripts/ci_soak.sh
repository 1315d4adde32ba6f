#!/usr/bin/env bash
# Soak test of CI: run .ci/run N times, each from a fresh clone, optionally beside busy loops.
set -uo pipefail

usage() {
    cat <<'EOF'
Usage: scripts/ci_soak.sh N [--hogs K] [--ref REF] [--keep]

Run the CI entry point (.ci/run, i.e. `make test`) N times. Every run starts from a fresh
`git clone` of the repository this script lives in, checked out at REF (default HEAD), in a
new empty temporary directory (so it also builds its own .venv), with CI=true, stdin from
/dev/null, ROS_AUTOMATIC_DISCOVERY_RANGE=LOCALHOST and its own ROS_DOMAIN_ID (10, 20, ...,
190, then again from 10; the test modules add offsets below 10, so ids stay below 200).

  N           number of runs (a positive integer)
  --hogs K    keep K busy-loop processes running during the runs (default 0); they are
              started before the first run and killed on exit, Ctrl-C included
  --ref REF   commit, branch or tag to test (default HEAD; must be committed)
  --keep      keep the clones (default: each clone is removed after its run)
  -h, --help  show this help

Each run's output goes to <log dir>/run-<i>.log; the log dir is printed first and last.
At the end it prints `passed P of N` with the number of hogs and, for every failed run, its
exit code and the failing tests (pytest's FAILED / ERROR summary lines).
Exit status: 0 only if every run passed; 2 on a usage error.
EOF
}

die_usage() {
    echo "ci_soak.sh: $1" >&2
    echo "Try 'scripts/ci_soak.sh --help'." >&2
    exit 2
}

N=''
HOGS=0
REF=HEAD
KEEP=0
while [ $# -gt 0 ]; do
    case "$1" in
        -h|--help) usage; exit 0 ;;
        --hogs)
            [ $# -ge 2 ] || die_usage '--hogs: expected a number'
            HOGS=$2; shift 2 ;;
        --hogs=*) HOGS=${1#--hogs=}; shift ;;
        --ref)
            [ $# -ge 2 ] || die_usage '--ref: expected a commit, branch or tag'
            REF=$2; shift 2 ;;
        --ref=*) REF=${1#--ref=}; shift ;;
        --keep) KEEP=1; shift ;;
        -*) die_usage "unknown option '$1'" ;;
        *)
            [ -z "$N" ] || die_usage "unexpected argument '$1'"
            N=$1; shift ;;
    esac
done
[ -n "$N" ] || die_usage 'N: expected the number of runs'
[[ "$N" =~ ^[0-9]+$ ]] && [ "$N" -ge 1 ] || die_usage "N: expected a positive integer, got '$N'"
[[ "$HOGS" =~ ^[0-9]+$ ]] || die_usage "--hogs: expected a non-negative integer, got '$HOGS'"

SRC=$(git -C "$(dirname "$0")" rev-parse --show-toplevel 2>/dev/null) \
    || { echo 'ci_soak.sh: the script is not inside a git repository' >&2; exit 2; }
SHA=$(git -C "$SRC" rev-parse --verify --quiet "$REF^{commit}") \
    || { echo "ci_soak.sh: --ref: '$REF' is not a commit of $SRC" >&2; exit 2; }

# Network rule: every ROS process of the runs discovers peers on localhost only.
export ROS_AUTOMATIC_DISCOVERY_RANGE=LOCALHOST

# exec argv[1:] as the leader of a new session, SIGINT/SIGQUIT at their defaults
SESSION_EXEC='import os, signal, sys
for s in (signal.SIGINT, signal.SIGQUIT):
    signal.signal(s, signal.SIG_DFL)
os.setsid()
os.execv(sys.argv[1], sys.argv[1:])'

LOG_DIR=$(mktemp -d "${TMPDIR:-/tmp}/ci_soak_logs.XXXXXX")
HOG_PIDS=()
RUN_PID=''
CLONE=''

cleanup() {
    if [ -n "$RUN_PID" ] && kill -0 "$RUN_PID" 2>/dev/null; then
        kill -TERM -- "-$RUN_PID" 2>/dev/null
        sleep 2
        kill -KILL -- "-$RUN_PID" 2>/dev/null
    fi
    for pid in "${HOG_PIDS[@]}"; do
        kill "$pid" 2>/dev/null
    done
    for pid in "${HOG_PIDS[@]}"; do
        wait "$pid" 2>/dev/null
    done
    HOG_PIDS=()
    if [ -n "$CLONE" ] && [ "$KEEP" -eq 0 ]; then
        rm -rf "$CLONE"
    fi
}
on_signal() {
    echo
    echo "ci_soak.sh: interrupted; logs in $LOG_DIR" >&2
    exit 130  # the EXIT trap cleans up
}
trap cleanup EXIT
trap on_signal INT TERM HUP

echo "ci_soak: $N run(s) of .ci/run at $(git -C "$SRC" log -1 --format='%h %s' "$SHA")"
echo "ci_soak: source $SRC, $HOGS hog(s), logs in $LOG_DIR"

for _ in $(seq 1 "$HOGS"); do
    ( trap - INT TERM HUP; exec sh -c 'while :; do :; done' ) </dev/null >/dev/null 2>&1 &
    HOG_PIDS+=("$!")
done

PASSED=0
FAILED_RUNS=()
for i in $(seq 1 "$N"); do
    DOMAIN=$(( ( (i - 1) % 19 + 1 ) * 10 ))
    LOG="$LOG_DIR/run-$i.log"
    CLONE=$(mktemp -d "${TMPDIR:-/tmp}/ci_soak_run$i.XXXXXX")
    start=$SECONDS
    {
        echo "# ci_soak run $i of $N: commit $SHA, ROS_DOMAIN_ID=$DOMAIN, $HOGS hog(s), $CLONE"
        git clone --quiet --no-checkout "$SRC" "$CLONE/repo" \
            && git -C "$CLONE/repo" checkout --quiet --detach "$SHA"
    } >"$LOG" 2>&1
    rc=$?
    if [ "$rc" -eq 0 ]; then
        # a clean environment (nothing of the caller's Python or ROS setup leaks in) and
        # a session of its own, with SIGINT and SIGQUIT back to their defaults: a background
        # command of a script starts with them ignored, and the tests stop nodes with SIGINT
        (cd "$CLONE/repo" && exec env -u PYTHONPATH -u PYTHONHOME -u VIRTUAL_ENV \
            -u AMENT_PREFIX_PATH -u PYTEST_ADDOPTS CI=true ROS_DOMAIN_ID="$DOMAIN" \
            ROS_AUTOMATIC_DISCOVERY_RANGE=LOCALHOST \
            python3 -c "$SESSION_EXEC" ./.ci/run) </dev/null >>"$LOG" 2>&1 &
        RUN_PID=$!
        wait "$RUN_PID"
        rc=$?
        RUN_PID=''
    else
        echo "# the clone failed" >>"$LOG"
    fi
    if [ "$rc" -eq 0 ]; then
        PASSED=$((PASSED + 1))
        verdict=passed
    else
        FAILED_RUNS+=("$i:$rc:$DOMAIN")
        verdict="FAILED (exit $rc)"
    fi
    echo "ci_soak: run $i/$N (ROS_DOMAIN_ID=$DOMAIN) $verdict in $((SECONDS - start)) s"
    if [ "$KEEP" -eq 0 ]; then
        rm -rf "$CLONE"
    else
        echo "ci_soak:   clone kept in $CLONE/repo"
    fi
    CLONE=''
done

echo
echo "passed $PASSED of $N ($HOGS hog(s))"
for entry in "${FAILED_RUNS[@]}"; do
    IFS=: read -r i rc domain <<<"$entry"
    echo "run $i (ROS_DOMAIN_ID=$domain): exit $rc, log $LOG_DIR/run-$i.log"
    tests=$(grep -E '^(FAILED|ERROR) ' "$LOG_DIR/run-$i.log" | sed -E 's/ - .*//' | sort -u)
    if [ -n "$tests" ]; then
        echo "$tests" | sed 's/^/  /'
    else
        echo '  (no FAILED/ERROR summary line: the run stopped before or outside pytest; see the log)'
    fi
done
echo "logs in $LOG_DIR"
[ "$PASSED" -eq "$N" ]
