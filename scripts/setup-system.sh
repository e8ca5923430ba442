#!/usr/bin/env bash
# Installs the system packages vkray needs to build and to trace on a CPU-only machine:
# a Vulkan loader, Mesa's lavapipe (>= 24.1, the first with acceleration structures and ray
# queries), glslc/spirv-tools for the shaders, the Khronos validation layers for the tests, and
# libusb (Open3D's wheel links it: the oracle of vkray.open3d's tests).
# Debian bookworm ships Mesa 22.3, so there the newer Mesa comes from bookworm-backports.
# An installed GPU driver is left alone: Mesa's ICDs are installed beside it, never instead.
set -euo pipefail

as_root() { if [ "$(id -u)" = 0 ]; then "$@"; else sudo "$@"; fi; }

packages=(libvulkan1 glslc spirv-tools vulkan-validationlayers vulkan-tools libusb-1.0-0)
. /etc/os-release
if [ "${ID:-}" = debian ] && [ "${VERSION_CODENAME:-}" = bookworm ]; then
  list=/etc/apt/sources.list.d/vkray-bookworm-backports.list
  if ! grep -rqs "bookworm-backports" /etc/apt/sources.list /etc/apt/sources.list.d/; then
    echo "deb http://deb.debian.org/debian bookworm-backports main" | as_root tee "$list" >/dev/null
  fi
  mesa_target=(-t bookworm-backports)
else
  mesa_target=()
fi

missing=()
for p in "${packages[@]}" mesa-vulkan-drivers; do
  dpkg-query -W -f='${Status}' "$p" 2>/dev/null | grep -q "ok installed" || missing+=("$p")
done
mesa_version=$(dpkg-query -W -f='${Version}' mesa-vulkan-drivers 2>/dev/null || true)
if [ -n "$mesa_version" ] && dpkg --compare-versions "$mesa_version" lt 24.1; then
  missing+=(mesa-vulkan-drivers)
fi

if [ ${#missing[@]} -gt 0 ]; then
  export DEBIAN_FRONTEND=noninteractive
  as_root apt-get update -qq
  as_root apt-get install -y -qq --no-install-recommends "${packages[@]}"
  as_root apt-get install -y -qq --no-install-recommends "${mesa_target[@]}" mesa-vulkan-drivers
fi
