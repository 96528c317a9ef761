python3 -m pip install -q --no-index --no-deps --no-compile --no-cache-dir --upgrade --target /tmp/site .whl/*.whl && export PYTHONPATH=/tmp/site:$PWD || exit; export PYTHONUNBUFFERED=1
python3 benchmarks/flip_proxy.py --damages leg0,leg2,leg3,leg5,leg1 --robots 128 --actions 3 2>&1 | tee $OUT/flip_proxy.log
cp benchmarks/results/flip_proxy_*.json $OUT/
