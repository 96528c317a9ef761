python3 -m pip install -q --no-index --no-deps --no-compile --no-cache-dir --upgrade --target /tmp/site .whl/*.whl && export PYTHONPATH=/tmp/site:$PWD || exit; export PYTHONUNBUFFERED=1
python3 benchmarks/flip_proxy.py --damages leg2,leg3,leg0,leg5 --robots 128 --actions 3 --ways rte,sparing \
  --models raised,light,touchless --label _why 2>&1 | tee $OUT/flip_proxy_why.log
cp benchmarks/results/flip_proxy_why_*.json $OUT/
