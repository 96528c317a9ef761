python3 -m pip install -q --no-index --no-deps --no-compile --no-cache-dir --upgrade --target /tmp/site .whl/*.whl && export PYTHONPATH=/tmp/site:$PWD || exit; export PYTHONUNBUFFERED=1
S=benchmarks/results/hte_spare_gpu_NVIDIA_H100_2026-11-25/sets_call.sh
t0=$(date +%s)
python3 -m experiments.pattern_ends --max-lifted 2 --no-progress 2>&1 | grep -v -i warn | tail -3
cp assets/hbr_gpu/pattern_ends_sparing.npz $OUT/; echo ends $(( $(date +%s) - t0 )) s
bash $S middle_raised_m "--variant rte,perfect-measured,hte-measured,hte-sensed --damage leg1,leg4,legs1+4 --damage-model raised --seed 2"
bash $S protocol_raised_m "--variant rte,perfect-measured,hte-measured --damage all --damage-model raised --seed 1"
