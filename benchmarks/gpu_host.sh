#!/usr/bin/env bash
# The GPU-host checks of issue 46 as one run (about 8 minutes on an H200 host of 16 cores):
#   1. the Monte Carlo kernel on the GPU: `bench.py --only-mc` (N = 1e3, 1e4, 1e5 against the
#      SciPy lfilter loop on one host core; float64 states, float32 noise draws) and N = 1e6
#      alone (`--mc-rate`);
#   2. the quick report with `--device auto` (latency-bound work on the host CPU, the sweeps
#      on the GPU) against `--device cpu`, run at the same time on the two halves of the
#      host's cores (taskset), each with an empty compile cache of its own, so that neither
#      reuses the other's compiled programs.
# Usage: PYTHONPATH=. benchmarks/gpu_host.sh OUT_DIR   (QUICK=1: bench.py --quick, no report;
# SKIP_MC=1: the reports alone; REPORT_LIMIT: each report's time limit [s], default 300)
# Writes OUT_DIR/host.txt, mc/mc.json, mc.log, mc_1e6.json, report_{auto,cpu}.log and
# report_{auto,cpu}.json (each study's wall time and where its work ran).
set -uo pipefail
out=${1:?usage: gpu_host.sh OUT_DIR}
mkdir -p "$out"
py=${PYTHON:-python3}
export PYTHONUNBUFFERED=1
quick=${QUICK:-}
{
    nvidia-smi -L 2>&1 || echo "no nvidia-smi"
    $py -c "import jax, os; print('jax', jax.__version__, jax.devices(), os.cpu_count(), 'cpus')"
    git rev-parse HEAD 2>/dev/null || true
} > "$out/host.txt" 2>&1

if [ -z "${SKIP_MC:-}" ]; then
timeout 240 $py benchmarks/bench.py --only-mc ${quick:+--quick} --out "$out/mc" > "$out/mc.log" 2>&1
echo "bench rc $?" >> "$out/mc.log"
[ -n "$quick" ] && exit 0
timeout 120 $py benchmarks/bench.py --mc-rate 1000000 > "$out/mc_1e6.json" 2>> "$out/mc.log"
echo "N=1e6 rc $?" >> "$out/mc.log"
fi

cores=$(nproc)
half=$((cores / 2))
report() {  # report DEVICE CPU_LIST
    local root=/tmp/gpu_host_$1 start=$SECONDS
    ACCEL_JAX_CACHE_DIR=/tmp/gpu_host_cache_$1 timeout "${REPORT_LIMIT:-300}" taskset -c "$2" \
        $py -c 'import sys; from accel_jax.cli import main; sys.exit(main())' \
        report --quick --no-progress --device "$1" --out "$root/report" \
        > "$out/report_$1.log" 2>&1
    local rc=$?
    echo "rc $rc, wall $((SECONDS - start)) s on cpus $2" >> "$out/report_$1.log"
    $py - "$root" "$out/report_$1.json" "$((SECONDS - start))" "$rc" <<'EOF'
import json, sys
from pathlib import Path
root, dest, wall, rc = Path(sys.argv[1]), sys.argv[2], int(sys.argv[3]), int(sys.argv[4])
studies = {}
for marker in sorted(root.glob("*/.accel_jax_run.json")):
    row = json.loads(marker.read_text())
    result = marker.parent / "result.json"
    placement = None
    if result.exists():
        placement = json.loads(result.read_text()).get("provenance", {}).get("placement")
    studies[marker.parent.name] = {
        "seconds": row.get("seconds"), "complete": row.get("complete"), "placement": placement
    }
Path(dest).write_text(json.dumps({"wall_s": wall, "rc": rc, "studies": studies}, indent=1))
EOF
}
report auto "0-$((half - 1))" &
report cpu "$half-$((cores - 1))" &
wait
[ -z "${SKIP_MC:-}" ] && tail -n 12 "$out/mc.log" && cat "$out/mc_1e6.json"
tail -n 2 "$out"/report_*.log
