#!/usr/bin/env bash
# Install the Debian packages cm2optics needs, only those missing; no-op when all are there.
#   libllvm19   Mitsuba 3 / Dr.Jit LLVM (CPU) variants (Debian's default LLVM 14/15 fail)
#   libegl1 …   off-screen rendering of part pictures (VTK through EGL) and OpenCASCADE
set -euo pipefail
packages=(libllvm19 libegl1 libegl-mesa0 libgl1 libglx-mesa0 libx11-6 libxrender1 libgomp1)
missing=()
for pkg in "${packages[@]}"; do
  dpkg-query -W -f='${Status}' "$pkg" 2>/dev/null | grep -q "install ok installed" || missing+=("$pkg")
done
[ ${#missing[@]} -eq 0 ] && exit 0
echo "installing Debian packages: ${missing[*]}"
if [ "$(id -u)" -ne 0 ]; then
  SUDO=sudo
else
  SUDO=
fi
$SUDO apt-get update -qq
DEBIAN_FRONTEND=noninteractive $SUDO apt-get install -y -qq --no-install-recommends "${missing[@]}"
