python3 -m pip install -q --no-index --no-deps --no-compile --no-cache-dir --upgrade --target /tmp/site .whl/*.whl && export PYTHONPATH=/tmp/site:$PWD || exit; export PYTHONUNBUFFERED=1
S=benchmarks/results/hte_spare_gpu_NVIDIA_H100_2026-11-25/sets_call.sh
bash $S middle_raised_s3 "--variant rte,hte-spare,hte-measured,perfect-spare --damage leg1,leg4,legs1+4 --damage-model raised --seed 3"
bash $S protocol_raised_spare "--variant rte,hte-spare --damage all --damage-model raised --seed 1"
bash $S protocol_locked_spare "--variant rte,hte-spare --damage all --damage-model locked --seed 1"
