#!/bin/sh
# The full peer matrix of benchmarks/RESULTS.md: dense and settle, N = 1e4 and 1e5,
# 1 and 2 threads, 3 repeats each; one JSON report per line in $OUT. On a shared
# machine each run first waits (up to 60 s) for the others to go quiet, and a run
# during which other processes used more than 25 % of the CPUs is done once more.
#   sh benchmarks/run_peers_matrix.sh [extra peers.py options, e.g. --demstep-src DIR]
#   PROBLEMS=settle SIZES=100000 THREADS=2 sh benchmarks/run_peers_matrix.sh   # a part
set -e
HERE=$(dirname "$0")
OUT=${OUT:-$HERE/results/peers-$(date +%Y%m%d).jsonl}
mkdir -p "$(dirname "$OUT")"
for problem in ${PROBLEMS:-dense settle}; do
  for n in ${SIZES:-10000 100000}; do
    for threads in ${THREADS:-1 2}; do
      python "$HERE/peers.py" --problem $problem --n $n --threads $threads --repeat 3 --json \
        --idle-wait 60 --max-foreign 0.25 --retries 1 "$@" >> "$OUT"
    done
  done
done
echo "results in $OUT"
