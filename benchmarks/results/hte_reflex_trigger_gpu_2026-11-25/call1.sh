# call 1 (nvidia-h100-x2): GPU 0: issue 19's single-GPU throughput at batch 32768 (batch_size.py and
# scaling.py, same run), then half of the reflex-trigger flip-proxy sweep; GPU 1: the other half.
python3 -m pip install -q --no-index --no-deps --no-compile --no-cache-dir --upgrade --target /tmp/site .whl/*.whl && export PYTHONPATH=/tmp/site:$PWD || exit; export PYTHONUNBUFFERED=1
nvidia-smi --query-gpu=name --format=csv,noheader
D=benchmarks/results/hte_reflex_trigger_gpu_2026-11-25
FP="python3 benchmarks/flip_proxy.py --damages leg0,leg2,leg3,leg5,leg1,leg4,legs1+4 --robots 256 --actions 3 --ways sparing --models raised"
( export CUDA_VISIBLE_DEVICES=1
  $FP --reflex-tilt 0.3/0/1,0.3/0/2,0.4/0.2,0.3/0.15/1 --label _trigger_b > $OUT/flip_b.log 2>&1 ) &
( export CUDA_VISIBLE_DEVICES=0
  python3 benchmarks/batch_size.py --min-batch 32768 --max-batch 32768 --repeats 5 --native-batches "" --out $OUT/batch_size_32768.json > $OUT/batch_size.log 2>&1
  python3 benchmarks/scaling.py --devices 1 --batch 32768 --episodes 0 --repeats 5 --out $OUT/scaling_1gpu_32768.json > $OUT/scaling_1gpu.log 2>&1
  $FP --reflex-tilt 0,0.3,0.3/0.15,0.4 --label _trigger_a > $OUT/flip_a.log 2>&1 )
wait
cp benchmarks/results/flip_proxy_trigger_*.json $OUT/
tail -3 $OUT/*.log
