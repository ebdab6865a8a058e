#!/usr/bin/env bash
# Run a grid from a worktree pinned at one commit, and bring its finished trials home.
#
#   experiments/pinned.sh start COMMIT GRID.toml OUT [MAX_CONCURRENT]
#   experiments/pinned.sh queue COMMIT GRID.toml OUT [COMMIT GRID.toml OUT ...]
#   experiments/pinned.sh collect COMMIT OUT
#
# start: makes ../exp-<sha> (git worktree at COMMIT, its own .venv) if it is missing,
#   seeds its OUT with what main's OUT holds (finished trials, runs.json) without
#   overwriting anything there, and starts `skyloop experiment run GRID --out OUT` in
#   the background at nice 19 (log: ../grid-<name of OUT>.log). Work on main then cannot
#   change the code under the grid, and the rerun continues it: finished trials are
#   skipped, started ones resume from their checkpoint (in the worktree only: a machine
#   that loses the worktree loses the trials in progress, not the finished ones).
# queue: the grids one after another in the background (two trials at a time each),
#   each as `start` runs it, each once no other `skyloop experiment run` is running (so a
#   queue started beside a running grid waits for it); the machine never idles between
#   grids. Log: ../grid-queue.log. Every argument is checked before anything starts.
#   `run` (same arguments as start) is one grid in the foreground; queue calls it.
# collect: copies every finished trial (result.json) of the worktree's OUT into main's
#   (a file newer on main, such as a selection.jsonl validation appended to, is kept),
#   without checkpoints or TensorBoard events (experiments/.gitignore keeps them out of
#   git anyway), with runs.json and grid.toml; then write the report on main:
#   skyloop experiment report OUT --eval-episodes 200
#
# Example (issue 10's static grid at the commit it began on):
#   experiments/pinned.sh start ed39746 experiments/paper_static.toml experiments/paper_static
set -euo pipefail
self=$(cd "$(dirname "$0")" && pwd)/$(basename "$0")
cd "$(dirname "$0")/.."
main=$(pwd)
# what queue waits on (a grid's command line, `python -m skyloop experiment run` or the
# `skyloop experiment run` console script; `ru[n]` keeps it from matching itself), and
# how often it looks (the tests set both)
wait_pattern=${PINNED_WAIT_PATTERN:-skyloop experiment ru[n] }
poll_s=${PINNED_POLL_S:-30}
locks=$(dirname "$main")  # grid-<name of OUT>.lock (one run per OUT), grid-queue.lock

usage() { sed -n '4,6p' "$self" | sed 's/^# *//' >&2; exit 2; }
die() { echo "pinned.sh: $*" >&2; exit 2; }

# the full sha of COMMIT, or exit 2 naming it
sha_of() {
    git rev-parse "$1^{commit}" 2>/dev/null \
        || die "COMMIT '$1' is not a commit of this repository"
}

# COMMIT GRID: exit 2 unless GRID is a file at COMMIT
check_grid() {
    local sha
    sha=$(sha_of "$1")
    git cat-file -e "$sha:$2" 2>/dev/null || die "GRID '$2': no such file at commit ${sha:0:7}"
}

running() { pgrep -f "experiment run $1 --out $2( |\$)" >/dev/null; }

# COMMIT OUT: lay out ../exp-<sha> (worktree, .venv) and its OUT; prints the worktree
prepare() {
    local sha wt out=${2%/}
    sha=$(sha_of "$1")
    wt=$(dirname "$main")/exp-${sha:0:7}
    if [ ! -d "$wt" ]; then
        git worktree prune
        git worktree add --detach "$wt" "$sha" >/dev/null
    fi
    make -s -C "$wt" .venv/.installed >&2
    if [ -d "$out" ]; then
        mkdir -p "$wt/$out"
        cp -rn "$out/." "$wt/$out/"  # never overwrites the worktree's newer state
    fi
    # The checkpoints are git-ignored (experiments/.gitignore), and a machine that keeps a
    # checkout's untracked files across sessions but not its ignored ones (ours) would
    # lose them: un-ignore them in the worktree only (collect never copies them).
    mkdir -p "$wt/$out"
    printf '# worktree only: keep checkpoints visible to git (see pinned.sh)\n!checkpoint.pt\n' \
        >"$wt/$out/.gitignore"
    echo "$wt"
}

# COMMIT GRID OUT CONC: prepare, then run the grid in the foreground, holding OUT's lock
# (inherited by the grid's process: a second run of the same OUT is refused meanwhile)
run_grid() {
    local wt grid=$2 out=${3%/} conc=$4
    exec 9>"$locks/grid-$(basename "$out").lock"
    flock -n 9 || die "a grid with --out $out is already running (lock $locks/grid-$(basename "$out").lock)"
    wt=$(prepare "$1" "$out")
    echo "pinned.sh: $(date -u +%FT%TZ) $grid from $wt -> $wt/$out"
    cd "$wt" && nice -n 19 .venv/bin/python -m skyloop experiment run "$grid" --out "$out" \
        --max-concurrent "$conc"
}

[ $# -ge 3 ] || usage
cmd=$1
case $cmd in
run|start)
    [ $# -ge 4 ] || usage
    check_grid "$2" "$3"
    running "$3" "${4%/}" && die "a grid with --out ${4%/} is already running (pgrep -af 'experiment run')"
    if [ "$cmd" = run ]; then
        run_grid "$2" "$3" "$4" "${5:-2}"
        exit
    fi
    wt=$(prepare "$2" "$4")  # in the foreground: a failing worktree or venv shows here
    log=$(dirname "$main")/grid-$(basename "${4%/}").log
    (setsid nohup bash "$self" run "$(sha_of "$2")" "$3" "$4" "${5:-2}" >>"$log" 2>&1 </dev/null &)
    echo "pinned.sh: $3 running from $wt; log $log"
    ;;
queue)
    shift
    [ $(($# % 3)) -eq 0 ] || die "queue takes COMMIT GRID.toml OUT triples, got $# arguments"
    args=("$@")
    for ((i = 0; i < $#; i += 3)); do
        check_grid "${args[i]}" "${args[i+1]}"
        args[i]=$(sha_of "${args[i]}")  # pinned now: HEAD or a branch may move meanwhile
    done
    # one queue at a time: the lock is held by the background queue (and its grids),
    # which inherit this descriptor
    exec 8>"$locks/grid-queue.lock"
    flock -n 8 || die "a queue is already running (lock $locks/grid-queue.lock; pgrep -af 'queue')"
    log=$(dirname "$main")/grid-queue.log
    # this script as queued (beside it, so that it finds main the same way; git-ignored)
    script=$(mktemp "$main/experiments/.pinned-queue-XXXXXX.sh")
    cp "$self" "$script"
    # one grid at a time: wait while any grid runs (this queue's or one started before it)
    # (the pattern goes by the environment: in the queue's own command line, pgrep would
    # find it there)
    (export PINNED_WAIT_PATTERN=$wait_pattern PINNED_POLL_S=$poll_s
     setsid nohup bash -c '
        script=$1; shift
        while [ $# -ge 3 ]; do
            while pgrep -f "$PINNED_WAIT_PATTERN" >/dev/null; do sleep "$PINNED_POLL_S"; done
            bash "$script" run "$1" "$2" "$3" 2 || echo "pinned.sh: $2 ended with status $?"
            shift 3
        done
        rm -f "$script"' queue "$script" "${args[@]}" >>"$log" 2>&1 </dev/null &)
    echo "pinned.sh: queued $(($# / 3)) grid(s); log $log"
    ;;
collect)
    sha=$(sha_of "$2")
    wt=$(dirname "$main")/exp-${sha:0:7}
    out=${3%/}
    [ -d "$wt/$out" ] || die "$wt/$out: no such directory"
    n=0
    for result in "$wt/$out"/*/result.json; do
        [ -f "$result" ] || continue
        trial=$(dirname "$result")
        dest=$out/$(basename "$trial")
        mkdir -p "$dest"
        (cd "$trial" && tar cf - --exclude=checkpoint.pt --exclude=checkpoint.pt.tmp \
            --exclude=tb .) | (cd "$dest" && tar xf - --keep-newer-files --warning=no-ignore-newer)
        n=$((n + 1))
    done
    for f in runs.json grid.toml; do
        [ -f "$wt/$out/$f" ] && cp "$wt/$out/$f" "$out/$f"
    done
    echo "pinned.sh: $n finished trial(s) of $wt/$out in $out; now:"
    echo "  skyloop experiment report $out --eval-episodes 200"
    ;;
*) usage ;;
esac
