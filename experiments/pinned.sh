#!/usr/bin/env bash
# Run a grid from a worktree pinned at one commit, and bring its finished trials home.
#
#   experiments/pinned.sh start COMMIT GRID.toml OUT [MAX_CONCURRENT]
#   experiments/pinned.sh collect COMMIT OUT
#
# start: makes ../exp-<sha> (git worktree at COMMIT, its own .venv) if it is missing,
#   seeds its OUT with what main's OUT holds (finished trials, runs.json) without
#   overwriting anything there, and starts `skyloop experiment run GRID --out OUT` in
#   the background at nice 19 (log: ../grid-<name of OUT>.log). Work on main then cannot
#   change the code under the grid, and the rerun continues it: finished trials are
#   skipped, started ones resume from their checkpoint (in the worktree only: a machine
#   that loses the worktree loses the trials in progress, not the finished ones).
# collect: copies every finished trial (result.json) of the worktree's OUT into main's,
#   without checkpoints or TensorBoard events (experiments/.gitignore keeps them out of
#   git anyway), with runs.json and grid.toml; then write the report on main:
#   skyloop experiment report OUT --eval-episodes 200
#
# Example (issue 10's static grid at the commit it began on):
#   experiments/pinned.sh start ed39746 experiments/paper_static.toml experiments/paper_static
set -euo pipefail
cd "$(dirname "$0")/.."
main=$(pwd)

usage() { sed -n '3,4p' "$0" | sed 's/^# *//' >&2; exit 2; }
[ $# -ge 3 ] || usage
cmd=$1 commit=$2
sha=$(git rev-parse --short=7 "$commit^{commit}" 2>/dev/null) \
    || { echo "pinned.sh: COMMIT '$commit' is not a commit of this repository" >&2; exit 2; }
wt=$(dirname "$main")/exp-$sha

case $cmd in
start)
    [ $# -ge 4 ] || usage
    grid=$3 out=${4%/} conc=${5:-2}
    git cat-file -e "$sha:$grid" 2>/dev/null \
        || { echo "pinned.sh: GRID '$grid': no such file at commit $sha" >&2; exit 2; }
    if pgrep -f "experiment run $grid --out $out( |\$)" >/dev/null; then
        echo "pinned.sh: a grid with --out $out is already running (pgrep -af 'experiment run')" >&2
        exit 2
    fi
    if [ ! -d "$wt" ]; then
        git worktree prune
        git worktree add --detach "$wt" "$sha" >/dev/null
    fi
    make -s -C "$wt" .venv/.installed
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
    log=$(dirname "$main")/grid-$(basename "$out").log
    (cd "$wt" && setsid nohup nice -n 19 .venv/bin/python -m skyloop experiment run \
        "$grid" --out "$out" --max-concurrent "$conc" >>"$log" 2>&1 </dev/null &)
    echo "pinned.sh: $grid running from $wt (commit $sha) -> $wt/$out; log $log"
    ;;
collect)
    out=${3%/}
    [ -d "$wt/$out" ] || { echo "pinned.sh: $wt/$out: no such directory" >&2; exit 2; }
    n=0
    for result in "$wt/$out"/*/result.json; do
        [ -f "$result" ] || continue
        trial=$(dirname "$result")
        dest=$out/$(basename "$trial")
        mkdir -p "$dest"
        (cd "$trial" && tar cf - --exclude=checkpoint.pt --exclude=checkpoint.pt.tmp \
            --exclude=tb .) | (cd "$dest" && tar xf -)
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
