#!/usr/bin/env bash
# The test command: sets up what the tests need on a fresh machine, then runs every test.
#
#   tests/run.sh                 # set up (idempotent, seconds when all is there), then every test
#   tests/run.sh --test daemon   # the same set-up, then only what `cargo test --release` is given
#   FWLIDAR_SETUP_ONLY=1 tests/run.sh   # set up only
#
# What the tests need beside the Rust toolchain, and why (each test names this command when
# what it needs is missing):
#   - Debian packages (apt-get, as root or through sudo): proj-bin (cs2cs, the geodesy
#     reference of tests/geodesy_proj.rs), gdal-bin (gdalinfo opens our COGs and VRTs),
#     chromium (loads the QC page headless, tests/daemon.rs), slurm-wlm and munge (a one-node
#     Slurm for tests/campaign_slurm.rs), python3-venv when `python3 -m venv` is missing.
#   - A Python venv in .venv with the field's own readers of our outputs, pinned in
#     tests/python/requirements.txt (laspy + lazrs, zarr + xarray + dask, rasterio + rio-cogeo,
#     scipy + scikit-image as references, prometheus_client, plyfile, pyproj).
# Everything comes from the package registries (Debian, PyPI, crates.io); nothing else is
# downloaded, and nothing is written outside .venv, target/ and the system's packages.
set -euo pipefail
cd "$(dirname "$0")/.."
repo="$(pwd)"

say() { printf '== %s\n' "$*"; }

# --- Debian packages -------------------------------------------------------------------------
# command -> package; a command is looked for on PATH and in the sbin folders (Slurm's and
# munge's daemons live in /usr/sbin).
need_apt=()
have() {
  command -v "$1" >/dev/null 2>&1 || [ -x "/usr/sbin/$1" ] || [ -x "/sbin/$1" ]
}
for pair in cs2cs:proj-bin gdalinfo:gdal-bin chromium:chromium groff:groff-base slurmctld:slurm-wlm \
  slurmd:slurm-wlm sbatch:slurm-wlm munged:munge; do
  cmd="${pair%%:*}"
  pkg="${pair#*:}"
  if ! have "$cmd"; then
    case " ${need_apt[*]-} " in *" $pkg "*) ;; *) need_apt+=("$pkg") ;; esac
  fi
done
if ! python3 -c 'import ensurepip, venv' >/dev/null 2>&1; then
  need_apt+=("python3-venv")
fi
if [ "${#need_apt[@]}" -gt 0 ]; then
  if [ "$(id -u)" = 0 ]; then
    sudo=()
  elif command -v sudo >/dev/null 2>&1 && sudo -n true 2>/dev/null; then
    sudo=(sudo -n)
  else
    echo "tests/run.sh: the tests need the Debian packages ${need_apt[*]}, and installing them" >&2
    echo "  needs root: run this as root, or 'sudo apt-get install ${need_apt[*]}' first" >&2
    exit 1
  fi
  say "installing Debian packages: ${need_apt[*]} (apt-get; a few minutes the first time)"
  export DEBIAN_FRONTEND=noninteractive
  "${sudo[@]}" apt-get update -qq
  "${sudo[@]}" apt-get install -y -qq --no-install-recommends "${need_apt[@]}" >/dev/null
fi
for cmd in cs2cs gdalinfo chromium slurmctld munged; do
  have "$cmd" || { echo "tests/run.sh: $cmd is still missing after apt-get" >&2; exit 1; }
done

# --- Python venv -----------------------------------------------------------------------------
req=tests/python/requirements.txt
stamp=.venv/.fwlidar-requirements
want="$(sha256sum "$req" | cut -d' ' -f1)"
if [ ! -x .venv/bin/python ]; then
  say "creating the Python venv .venv ($(python3 --version))"
  python3 -m venv .venv
fi
if [ "$(cat "$stamp" 2>/dev/null)" != "$want" ]; then
  say "installing the Python packages of $req into .venv (PyPI)"
  .venv/bin/python -m pip install -q --disable-pip-version-check -r "$req"
  echo "$want" > "$stamp"
fi
say "ready: $(cs2cs 2>&1 | head -1 | cut -c1-40); GDAL $(gdalinfo --version | cut -d' ' -f2 | tr -d ,);" \
  "$(chromium --version 2>/dev/null | head -1); $(/usr/sbin/slurmctld -V 2>/dev/null || slurmctld -V);" \
  "Python packages as pinned in $req"

if [ "${FWLIDAR_SETUP_ONLY:-0}" = 1 ]; then
  exit 0
fi

# --- the tests -------------------------------------------------------------------------------
export FWLIDAR_PYTHON="$repo/.venv/bin/python"
say "cargo test --release $*"
cargo test --release "$@"
