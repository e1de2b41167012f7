#!/usr/bin/env bash
# Runs one of the README's two newcomer commands exactly as written there (the fenced block that
# follows the marker `<!-- command: NAME -->`), so CI and the README cannot drift apart.
set -euo pipefail
name="$1"
block=$(awk -v marker="<!-- command: $name -->" '
  $0 == marker { found = 1; next }
  found && /^```/ { if (inside) exit; inside = 1; next }
  inside { print }
' README.md)
[ -n "$block" ] || { echo "README.md has no command block named '$name'" >&2; exit 1; }
echo "+ $block"
bash -euo pipefail -c "$block"
