#!/usr/bin/env bash
# the demo's first start from an empty cache, two trees alternated (wall time to "Ready.")
# usage: notes/scripts/first_start_ab.sh ROUNDS OLD_TREE NEW_TREE (each a checkout of navapp)
for r in $(seq 1 ${1:-2}); do
 for tree in "$2" "$3"; do
  cache=$(mktemp -d); log=$(mktemp)
  port=$((18000 + RANDOM % 1000))
  t0=$(date +%s.%N)
  PYTHONPATH=$tree NAVAPP_CACHE=$cache python -m navapp serve --port $port --session $cache/session > $log 2>&1 &
  pid=$!
  for i in $(seq 1 900); do grep -q "Ready\." $log && break; sleep 0.5; done
  t1=$(date +%s.%N)
  echo "$tree round $r: $(echo "$t1 - $t0" | bc) s wall; $(grep -o 'Ready.*' $log | tail -1); load $(cut -d' ' -f1 /proc/loadavg)"
  kill $pid; wait $pid 2>/dev/null; rm -rf $cache $log
 done
done
