python3 -m pip install -q --no-index --no-deps --no-compile --no-cache-dir --upgrade --target /tmp/site .whl/*.whl && export PYTHONPATH=/tmp/site:$PWD || exit; export PYTHONUNBUFFERED=1
S=benchmarks/results/hte_corner_gpu_NVIDIA_H100_2026-11-25/sets_call.sh
nvidia-smi --query-gpu=name --format=csv,noheader
bash $S middle_raised_noreflex_s12 "--variant perfect-hte,hte-spare,rte --damage leg1,leg4,legs1+4 --damage-model raised --seed 12"
