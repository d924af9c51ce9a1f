#!/bin/bash
cd "$(dirname "$0")"
for t in "$@"; do
  mkdir -p corpus/$t artifacts/$t
  cargo +nightly fuzz run $t corpus/$t -- -max_total_time=60 -max_len=65536 -artifact_prefix=artifacts/$t/ > logs_$t.txt 2>&1
  echo "$t exit $? :: $(grep -E '^#[0-9]+' logs_$t.txt | tail -1)"
done
