#!/bin/sh
# Instructions per forwarded transaction of the gateway's own path (issue 12), robust
# on a loaded machine: bench/investigations/profile_gateway.py under callgrind at two lengths, the
# difference of the totals over the difference of the transactions (start-up cancels).
#
#     bench/investigations/callgrind_gateway.sh [BUS] [SHORT] [LONG]      (BUS: instant (default) or pty)
#
# Prints one JSON line: {"bus", "short", "long", "ir_short", "ir_long", "ir_per_tx"}.
set -eu
BUS=${1:-instant}
SHORT=${2:-300}
LONG=${3:-1300}
PY=${PYTHON:-$(dirname "$0")/../../.venv/bin/python}
OUT=$(mktemp -d)
trap 'rm -rf "$OUT"' EXIT
for n in "$SHORT" "$LONG"; do
    valgrind --tool=callgrind --callgrind-out-file="$OUT/cg.$n" \
        "$PY" "$(dirname "$0")/profile_gateway.py" --bus "$BUS" --transactions "$n" --json \
        >"$OUT/out.$n" 2>"$OUT/err.$n" || { cat "$OUT/err.$n" >&2; exit 1; }
done
ir() { grep '^summary:' "$OUT/cg.$1" | awk '{print $2}'; }
tx() { "$PY" -c 'import json,sys; print(json.loads(open(sys.argv[1]).read().splitlines()[-1])["transactions"])' "$OUT/out.$1"; }
"$PY" - "$BUS" "$SHORT" "$LONG" "$(ir "$SHORT")" "$(ir "$LONG")" "$(tx "$SHORT")" "$(tx "$LONG")" <<'PYEOF'
import json, sys
bus, short, long_, ir_s, ir_l, tx_s, tx_l = sys.argv[1:]
per = (int(ir_l) - int(ir_s)) / (int(tx_l) - int(tx_s))
print(json.dumps({"bus": bus, "short": int(tx_s), "long": int(tx_l), "ir_short": int(ir_s),
                  "ir_long": int(ir_l), "ir_per_tx": round(per)}))
PYEOF
