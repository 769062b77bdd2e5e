#!/bin/bash
# usage: fit.sh CLONE OUTDIR  -- a short on-grid marginal fit, fixed seed
cd $2 && rm -rf runs cache && PYTHONPATH=$1 exec /tmp/venv/bin/python -m otgb.cli fit --config $1/configs/pendulum.yaml '--data.hidden_effect=[]' --data.measured_path /work/grid/grid.csv --data.measurement_noise 0.02 --data.simulation_budget 6400 --trainer.max_steps 200 --trainer.val_check_interval 100 --trainer.enable_progress_bar false --data.cache_dir $2/cache --seed_everything 0
