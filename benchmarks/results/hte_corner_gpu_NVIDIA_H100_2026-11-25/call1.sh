python3 -m pip install -q --no-index --no-deps --no-compile --no-cache-dir --upgrade --target /tmp/site .whl/*.whl && export PYTHONPATH=/tmp/site:$PWD || exit; export PYTHONUNBUFFERED=1
S=benchmarks/results/hte_corner_gpu_NVIDIA_H100_2026-11-25/sets_call.sh
nvidia-smi --query-gpu=name --format=csv,noheader
bash $S corner_raised "--variant rte,hte-spare,perfect-spare,perfect-hte --damage leg0,leg2,leg3,leg5 --damage-model raised --seed 1" \
        protocol_locked_spare "--variant rte,hte-spare,perfect-spare --damage all --damage-model locked --seed 1" \
        middle_locked_spare "--variant rte,hte-spare,perfect-spare --damage leg1,leg4,legs1+4 --damage-model locked --seed 2"
