python3 -m pip install -q --no-index --no-deps --no-compile --no-cache-dir --upgrade --target /tmp/site .whl/*.whl && export PYTHONPATH=/tmp/site:$PWD || exit; export PYTHONUNBUFFERED=1
S=benchmarks/results/hte_corner_gpu_NVIDIA_H100_2026-11-25/sets_call.sh
nvidia-smi --query-gpu=name --format=csv,noheader
bash $S middle_raised_reflex_s12 "--variant perfect-hte,hte-spare,perfect-spare,hte,rte,2d-rte --damage leg1,leg4,legs1+4 --damage-model raised --reflex-tilt 0.3 --seed 12" \
        protocol_locked_reflex_s13 "--variant perfect-hte,hte-spare,hte,rte,2d-rte --damage all --damage-model locked --reflex-tilt 0.3 --seed 13"
