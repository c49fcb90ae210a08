#!/usr/bin/env bash
# Converts a dataset on a shared file system with a Slurm job array: task I runs
# `convert --shard I/N`. Each task writes its own manifest
# (rangegan-manifest.shard-I-of-N.jsonl); resubmitting the array resumes every shard.
#   sbatch deploy/slurm-array.sh /shared/recordings /shared/converted
# Keep --array=0-(N-1) and SHARDS=N in step.
#SBATCH --job-name=rangegan-convert
#SBATCH --array=0-7
#SBATCH --cpus-per-task=4
#SBATCH --mem=8G
#SBATCH --time=04:00:00
#SBATCH --output=rangegan-convert-%A-%a.log
set -euo pipefail

IN=${1:?usage: sbatch slurm-array.sh IN_DIR OUT_DIR}
OUT=${2:?usage: sbatch slurm-array.sh IN_DIR OUT_DIR}
SHARDS=${SHARDS:-8}

# Exit code 4: some files failed (their manifest lines say why); the others are done.
rangegan-mcap --threads "${SLURM_CPUS_PER_TASK:-1}" convert "$IN" "$OUT" \
  --shard "${SLURM_ARRAY_TASK_ID}/${SHARDS}" --quality fast
