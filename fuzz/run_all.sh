#!/bin/bash
# Runs every target for $1 seconds; prints libFuzzer's last status line per target.
cd "$(dirname "$0")"
for t in ray_triangle bvh_vs_brute_force environment_cdf png_texture gltf_import environment_file; do
  mkdir -p corpus/$t artifacts/$t
  cargo +nightly fuzz run $t corpus/$t -- -max_total_time=$1 -max_len=65536 -artifact_prefix=artifacts/$t/ > logs_$t.txt 2>&1
  echo "$t exit $? :: $(grep -E '^#[0-9]+' logs_$t.txt | tail -1)"
done
