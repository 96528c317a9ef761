#!/bin/bash
# usage: sets_call.sh NAME "ARGS" [NAME "ARGS" ...]: maze_eval --preset gpu --replicates 30 per set;
# statistics.json, summary.json, episodes.json and the log tail of each set into $OUT/sets.tgz
mkdir -p /tmp/res
while [ $# -gt 1 ]; do
  name=$1; args=$2; shift 2
  start=$(date +%s)
  python3 -m experiments.maze_eval --preset gpu --replicates 30 --no-progress --out /tmp/runs/$name $args > /tmp/$name.log 2>&1
  rc=$?
  mkdir -p /tmp/res/$name
  cp /tmp/runs/$name/statistics.json /tmp/runs/$name/summary.json /tmp/runs/$name/episodes.json /tmp/res/$name/ 2>/dev/null
  tail -8 /tmp/$name.log > /tmp/res/$name/log.txt
  echo "$name rc=$rc $(( $(date +%s) - start )) s"; cat /tmp/res/$name/log.txt
  tar czf $OUT/sets.tgz -C /tmp/res .
done
