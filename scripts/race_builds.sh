#!/usr/bin/env bash
# Races two builds of mlsss on one command, in balanced order (A B B A, repeated) with a pause
# before every run, and prints each run and the medians (wall and CPU from GNU time, peak
# resident memory, the stages' wall seconds when the command writes a pipeline report).
#
#   scripts/race_builds.sh BIN_A BIN_B CYCLES -- MLSSS_ARGS...
#
# e.g. the full-size process of scripts/speed_bench.sh, old build against new, 3 cycles (12 runs):
#
#   scripts/race_builds.sh /tmp/mlsss-old target/release/mlsss 3 -- process CAPTURE \
#       --calib truth --until fit --holdout 3 --components 4 --block 6
#
# Each run gets a fresh `--out` folder (appended to the arguments) under $RACE_OUT (default
# target/race-builds), deleted after the run but for its `report.json`. GAP=S sets the pause
# (default 6 s).
#
# Why balanced: on the 2-core build VM the run that comes second in a pair is favoured. Three
# sets of plain alternated pairs of two builds of the full-size process that differ by two
# skipped copies (outputs byte-identical) gave the second 17.0 against 18.6 s (5 pairs), 15.8
# against 16.5 s (4 pairs, the other order) and 15.5 against 16.1 s (4 pairs, 6 s pauses): up to
# 10 % from the order alone, as large as the changes being measured. A likely cause: the
# hypervisor takes back memory soon after the guest frees it (virtio-balloon free page
# reporting), and a page taken back costs 1-2 s per GiB to fault in again against ~0.1 s for one
# freed just before, so a run that starts soon after another inherits warm memory
# (scripts/page_reporting_race.sh measures it: the full-size process 10.93 s median with the
# reporting on, 10.22 s with it deferred). The balanced
# order cancels an order effect whatever its cause; the pause lets every run start from returned
# memory. How much 6 runs resolve: the same binary raced against itself (3 cycles, full-size
# process) gave medians 16.26 and 16.51 s wall, 28.6 and 29.1 CPU-s, the runs drifting from 17
# to 15 s within the race; differences below ~0.5 s are noise here.
# Paths (the builds, the capture, RACE_OUT) are taken as given, relative to where it is run.
set -euo pipefail
usage="usage: scripts/race_builds.sh BIN_A BIN_B CYCLES -- MLSSS_ARGS..."
[ $# -ge 5 ] && [ "$4" = "--" ] || { echo "$usage" >&2; exit 2; }
BIN_A=$1
BIN_B=$2
CYCLES=$3
shift 4
for bin in "$BIN_A" "$BIN_B"; do
    [ -x "$bin" ] || { echo "error: $bin is not an executable" >&2; exit 2; }
done
case $CYCLES in '' | *[!0-9]* | 0) echo "error: CYCLES must be a positive integer" >&2; exit 2 ;; esac
command -v /usr/bin/time >/dev/null || { echo "error: GNU time (/usr/bin/time) is missing: apt-get install time" >&2; exit 1; }
OUT=${RACE_OUT:-target/race-builds}
GAP=${GAP:-6}
mkdir -p "$OUT"
# A race that writes no pipeline report (the demo) would otherwise read an earlier race's.
rm -f "$OUT"/*.report.json "$OUT"/*.err
RESULTS="$OUT/results.tsv"
: > "$RESULTS"

# run LABEL BIN N MLSSS_ARGS...: run number N, timed, appended to the results.
run() {
    local label=$1 bin=$2 n=$3
    shift 3
    local dir="$OUT/$label-$n"
    rm -rf "$dir"
    sleep "$GAP"
    /usr/bin/time -f "%e %U %S %M" -o "$OUT/time" "$bin" "$@" --out "$dir" > /dev/null 2> "$OUT/$label-$n.err" \
        || { echo "error: $bin failed, see $OUT/$label-$n.err" >&2; exit 1; }
    read -r wall user sys peak < "$OUT/time"
    # Only the report is kept: a full-size run writes about 1.4 GB of artefacts.
    if [ -f "$dir/report.json" ]; then mv "$dir/report.json" "$OUT/$label-$n.report.json"; fi
    rm -rf "$dir"
    printf '%s\t%s\t%s\t%s\t%s\t%s\n' "$label" "$n" "$wall" "$user" "$sys" "$peak" >> "$RESULTS"
    awk -v l="$label" -v n="$n" -v w="$wall" -v u="$user" -v s="$sys" -v p="$peak" \
        'BEGIN { printf "%s run %s: %s s wall, %.1f CPU-s, %.2f GiB\n", l, n, w, u + s, p / 1048576 }'
}

# One untimed run first: the inputs may have left the page cache (a clean-clone test beside
# the capture evicted it once, and the first timed run took 80.6 s against 14-19 s).
echo "warm-up run (untimed) ..."
rm -rf "$OUT/warm-up" # a cached stage would warm nothing
"$BIN_A" "$@" --out "$OUT/warm-up" > /dev/null 2> "$OUT/warm-up.err" \
    || { echo "error: $BIN_A failed, see $OUT/warm-up.err" >&2; exit 1; }
rm -rf "$OUT/warm-up"

n=0
for _ in $(seq "$CYCLES"); do
    for label in A B B A; do
        n=$((n + 1))
        if [ "$label" = A ]; then run A "$BIN_A" "$n" "$@"; else run B "$BIN_B" "$n" "$@"; fi
    done
done

python3 - "$RESULTS" "$OUT" "$BIN_A" "$BIN_B" <<'EOF'
import json, statistics, sys
from collections import defaultdict
results, out, names = sys.argv[1], sys.argv[2], {"A": sys.argv[3], "B": sys.argv[4]}
runs = defaultdict(list)
for line in open(results):
    label, n, wall, user, sys_, peak = line.split("\t")
    stages = {}
    try:
        stages = json.load(open(f"{out}/{label}-{n}.report.json")).get("timing_s", {})
    except (OSError, ValueError):
        pass
    runs[label].append((float(wall), float(user) + float(sys_), int(peak) / 1048576, stages))
for label in "AB":
    v = runs[label]
    med = lambda xs: statistics.median(xs)
    print(f"{label} ({names[label]}, {len(v)} runs): median wall {med(r[0] for r in v):.2f} s "
          f"(range {min(r[0] for r in v):.2f}-{max(r[0] for r in v):.2f}), "
          f"median CPU {med(r[1] for r in v):.1f} s, largest peak {max(r[2] for r in v):.2f} GiB")
    stage_names = sorted({s for r in v for s in r[3]})
    if stage_names:
        print("   stage medians, wall s: " + ", ".join(
            f"{s} {med(r[3][s] for r in v if s in r[3]):.2f}" for s in stage_names))
EOF
