# Sourced by scripts/check.sh: the system packages the tests need (Debian/Ubuntu names). Missing
# ones are installed when this runs as root (or with password-less sudo) and apt-get exists;
# otherwise the script stops naming them. Nothing here is skipped: every test runs everywhere.
#   gcc, libc6-dev                the C ABI test compiles a C tracer
#   g++                           the C++ example renderer (rl-writer/examples) is built and run
#   python3, python3-pip          DuckDB and the ADBC Flight SQL driver (installed from PyPI below)
#   python3-venv                  the Python package's wheel is tested in a fresh venv
#   mesa-vulkan-drivers           lavapipe: the visualizer's pictures on Vulkan
#   libegl-mesa0, libgl1-mesa-dri llvmpipe: the same pictures on wgpu's GL backend
#   xvfb and X11 client libraries the test that opens the viewer's real window
#   openssl                       the query service's TLS test makes a self-signed certificate
rtvtk_missing_packages() {
  local need=()
  command -v cc >/dev/null || need+=(gcc libc6-dev)
  command -v c++ >/dev/null || need+=(g++)
  { command -v python3 >/dev/null && python3 -m pip --version >/dev/null 2>&1; } || need+=(python3 python3-pip)
  python3 -c "import ensurepip, venv" >/dev/null 2>&1 || need+=(python3-venv)
  ls /usr/share/vulkan/icd.d/*.json >/dev/null 2>&1 || need+=(mesa-vulkan-drivers libvulkan1)
  ls /usr/share/glvnd/egl_vendor.d/*mesa*.json >/dev/null 2>&1 || need+=(libegl1 libegl-mesa0 libgl1-mesa-dri)
  command -v Xvfb >/dev/null || need+=(xvfb xauth libxkbcommon-x11-0 libxcursor1 libxi6 libxrandr2 libx11-xcb1)
  command -v openssl >/dev/null || need+=(openssl)
  echo "${need[@]}"
}

missing="$(rtvtk_missing_packages)"
if [ -n "$missing" ]; then
  sudo=""
  if [ "$(id -u)" != 0 ] && command -v sudo >/dev/null && sudo -n true 2>/dev/null; then
    sudo="sudo -n"
  fi
  if command -v apt-get >/dev/null && { [ "$(id -u)" = 0 ] || [ -n "$sudo" ]; }; then
    echo "installing the system packages the tests need: $missing"
    $sudo apt-get update -q
    # shellcheck disable=SC2086
    DEBIAN_FRONTEND=noninteractive $sudo apt-get install -y -q --no-install-recommends $missing
  fi
  missing="$(rtvtk_missing_packages)"
  if [ -n "$missing" ]; then
    echo "the tests need these system packages, which are not installed: $missing" >&2
    echo "install them (Debian/Ubuntu: sudo apt-get install $missing) and run scripts/check.sh again" >&2
    exit 1
  fi
fi
# Mesa wants a private runtime directory (only to silence warnings; never fatal).
export XDG_RUNTIME_DIR="${XDG_RUNTIME_DIR:-$(mktemp -d)}"
mkdir -p "$XDG_RUNTIME_DIR" 2>/dev/null && chmod 700 "$XDG_RUNTIME_DIR" 2>/dev/null || true
