#!/bin/bash
# usage: sets_call.sh NAME "ARGS" [NAME "ARGS" ...]: maze_eval --preset gpu --replicates 30 per set; statistics.json and the log tail to $OUT/NAME
while [ $# -gt 1 ]; do
  name=$1; args=$2; shift 2
  start=$(date +%s)
  python3 -m experiments.maze_eval --preset gpu --replicates 30 --no-progress --out /tmp/runs/$name $args > /tmp/$name.log 2>&1
  rc=$?
  mkdir -p $OUT/$name; cp /tmp/runs/$name/statistics.json $OUT/$name/ 2>/dev/null
  tail -5 /tmp/$name.log > $OUT/$name/log.txt
  echo "$name rc=$rc $(( $(date +%s) - start )) s"
done
