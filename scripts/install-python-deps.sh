#!/usr/bin/env bash
# Install cm2optics and its pinned Python packages into the virtual environment $1 (default .venv).
# uv installs the same packages as pip in a fraction of the time (parallel downloads, a cache of
# unpacked wheels); pip does it alone where uv cannot be had. Local wheel folders that pip is
# given (PIP_FIND_LINKS or pip's find-links setting: e.g. the CPU build of torch) go to uv too.
set -euo pipefail
venv="${1:-.venv}"
py="$venv/bin/python"
[ -x "$py" ] || python3 -m venv "$venv"
links="${UV_FIND_LINKS:-${PIP_FIND_LINKS:-$("$py" -m pip config get global.find-links 2>/dev/null || true)}}"
find_links=()
for link in $links; do find_links+=(--find-links "$link"); done
if "$py" -m pip install --quiet uv 2>/dev/null && "$venv/bin/uv" pip install --quiet --python "$py" "${find_links[@]}" -e '.[test]'; then
  exit 0
fi
echo "uv could not install the packages; installing with pip instead" >&2
"$py" -m pip install --quiet -e '.[test]'
