python3 -m pip install -q --no-index --no-deps --no-compile --no-cache-dir --upgrade --target /tmp/site .whl/*.whl && export PYTHONPATH=/tmp/site:$PWD || exit; export PYTHONUNBUFFERED=1
nvidia-smi --query-gpu=name --format=csv,noheader
python3 benchmarks/flip_proxy.py --damages leg0,leg2,leg3,leg5,leg1 --robots 128 --actions 3 --ways rte,sparing \
    --models raised --reflex-tilt 0,0.3,0.5 --label _reflex 2>&1 | tee $OUT/flip_proxy_reflex.log
cp benchmarks/results/flip_proxy_reflex_*.json $OUT/
