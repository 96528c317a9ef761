#!/bin/bash
# usage: TAG=t sets_call.sh NAME "ARGS" [NAME "ARGS" ...]: maze_eval --preset gpu --replicates 30 per set, one
# after the other (the GPU of CUDA_VISIBLE_DEVICES); statistics.json, summary.json, episodes.json and the log
# tail of each set into $OUT/sets_$TAG.tgz after each set (two of these may run at once, with different TAGs)
res=/tmp/res_${TAG:-0}; mkdir -p $res
while [ $# -gt 1 ]; do
  name=$1; args=$2; shift 2
  start=$(date +%s)
  python3 -m experiments.maze_eval --preset gpu --replicates 30 --no-progress --out /tmp/runs/$name $args > /tmp/$name.log 2>&1
  rc=$?
  mkdir -p $res/$name
  cp /tmp/runs/$name/statistics.json /tmp/runs/$name/summary.json /tmp/runs/$name/episodes.json /tmp/runs/$name/config.json $res/$name/ 2>/dev/null
  tail -8 /tmp/$name.log > $res/$name/log.txt
  echo "$name rc=$rc $(( $(date +%s) - start )) s"; cat $res/$name/log.txt
  tar czf $OUT/sets_${TAG:-0}.tgz -C $res .
done
