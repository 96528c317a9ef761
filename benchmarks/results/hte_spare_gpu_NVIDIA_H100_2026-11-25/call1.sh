python3 -m pip install -q --no-index --no-deps --no-compile --no-cache-dir --upgrade --target /tmp/site .whl/*.whl && export PYTHONPATH=/tmp/site:$PWD || exit; export PYTHONUNBUFFERED=1
nvidia-smi --query-gpu=name --format=csv,noheader
S=benchmarks/results/hte_spare_gpu_NVIDIA_H100_2026-11-25/sets_call.sh
t0=$(date +%s)
python3 benchmarks/sparing_proxy.py --spare assets/hbr_gpu/spare.npz --damages leg1,leg4,legs1+4 --robots 256 --actions 4 --measured-ends --label _gpu > $OUT/proxy.log 2>&1; cp benchmarks/results/sparing_proxy_gpu*.json $OUT/ ; tail -12 $OUT/proxy.log; echo proxy $(( $(date +%s) - t0 )) s
bash $S middle_raised "--variant rte,perfect-hte,hte-sensed,perfect-spare,hte-spare --damage leg1,leg4,legs1+4 --damage-model raised --seed 2"
bash $S protocol_raised "--variant rte,perfect-spare,hte-spare --damage all --damage-model raised --seed 1"
