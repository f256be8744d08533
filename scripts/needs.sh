# Shared by scripts/demo and scripts/test: make sure the build's system needs are met on a
# Debian machine, installing what is missing when run as root (or with sudo), else naming it.
set -euo pipefail

need_debian_packages() {
    local missing=()
    for pkg in "$@"; do
        dpkg-query -W -f='${Status}' "$pkg" 2>/dev/null | grep -q "install ok installed" || missing+=("$pkg")
    done
    [ ${#missing[@]} -eq 0 ] && return 0
    local sudo=""
    if [ "$(id -u)" -ne 0 ]; then
        if command -v sudo >/dev/null; then sudo="sudo"; else
            echo "relight needs these Debian packages: ${missing[*]}" >&2
            echo "install them with: apt-get install ${missing[*]}" >&2
            exit 1
        fi
    fi
    echo "installing Debian packages: ${missing[*]}" >&2
    $sudo apt-get update -qq
    DEBIAN_FRONTEND=noninteractive $sudo apt-get install -y -qq --no-install-recommends "${missing[@]}" >&2
}

need_rust() {
    if ! command -v cargo >/dev/null; then
        echo "relight needs a Rust toolchain (1.88 or newer) with cargo, rustfmt and clippy:" >&2
        echo "  https://rustup.rs, then: rustup component add rustfmt clippy" >&2
        exit 1
    fi
}
