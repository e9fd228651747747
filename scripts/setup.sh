#!/usr/bin/env bash
# Idempotent set-up for dvla on a Debian-based machine.
#   1. system packages: a Vulkan driver for SAPIEN (Mesa lavapipe >= 24.3 when no GPU driver
#      is present), iproute2/iptables for emulated clusters, OpenSSH (client and server) for
#      remote nodes and their test;
#   2. Python packages: a CPU torch on machines without CUDA, the stock (CUDA) torch otherwise;
#   3. dvla itself, editable, with its test extras;
#   and with `test` (what `make test` runs): slurm-wlm and munge, and the `libero` extra with pip
#   held to the installed torch and numpy (DVLA_SETUP_LIBERO=0 skips it; the tests that need
#   either skip with a reason without them).
# Re-running it skips every step that is already done.
set -euo pipefail
cd "$(dirname "$0")/.."

PY=${PYTHON:-python3}
log() { printf '[setup] %s\n' "$*" >&2; }
SUDO=""
[ "$(id -u)" = 0 ] || SUDO="sudo"

have_gpu() { command -v nvidia-smi >/dev/null 2>&1 && nvidia-smi -L >/dev/null 2>&1; }

# --- 1. system packages --------------------------------------------------------------------
lavapipe_ok() {
  # dpkg version of Mesa's Vulkan drivers, compared against 24.3 (older lavapipe crashes SAPIEN).
  local v
  v=$(dpkg-query -W -f='${Version}' mesa-vulkan-drivers 2>/dev/null || true)
  [ -n "$v" ] && dpkg --compare-versions "$v" ge 24.3
}

add_backports_suite() {
  # Derive the mirror from the URIs this machine already uses for its main Debian suite, so
  # no registry host is written into the project.
  local codename uri list=/etc/apt/sources.list.d/dvla-backports.sources
  [ -f "$list" ] && return 0
  codename=$(. /etc/os-release && echo "${VERSION_CODENAME:-}")
  [ -n "$codename" ] || { log "cannot tell the Debian codename; install mesa-vulkan-drivers >= 24.3 by hand"; return 1; }
  uri=$( { grep -hE '^URIs:' /etc/apt/sources.list.d/*.sources 2>/dev/null | awk '{print $2}';
           grep -hE '^deb ' /etc/apt/sources.list 2>/dev/null | awk '{print $2}'; } \
         | grep -v -- '-security' | grep -i debian | head -n1 || true)
  [ -n "$uri" ] || { log "no Debian mirror found in the apt sources"; return 1; }
  log "adding ${codename}-backports from $uri"
  printf 'Types: deb\nURIs: %s\nSuites: %s-backports\nComponents: main\nSigned-By: /usr/share/keyrings/debian-archive-keyring.gpg\n' \
    "$uri" "$codename" | $SUDO tee "$list" >/dev/null
}

system_packages() {
  command -v apt-get >/dev/null 2>&1 || { log "no apt-get: install a Vulkan driver, iproute2, iptables and OpenSSH yourself"; return 0; }
  local need=()
  command -v ip >/dev/null 2>&1 || need+=(iproute2)
  command -v iptables >/dev/null 2>&1 || need+=(iptables)
  command -v tc >/dev/null 2>&1 || need+=(iproute2)
  # remote nodes are reached over ssh; the SSH test runs sshd inside a network namespace
  command -v ssh >/dev/null 2>&1 || need+=(openssh-client)
  [ -x /usr/sbin/sshd ] || need+=(openssh-server)
  dpkg-query -W -f='${Status}' libvulkan1 2>/dev/null | grep -q 'ok installed' || need+=(libvulkan1)
  # MuJoCo's offscreen rendering (LIBERO) through EGL: Mesa's on machines without a GPU driver
  local egl=()
  for pkg in libegl1 libegl-mesa0 libgl1-mesa-dri; do
    dpkg-query -W -f='${Status}' "$pkg" 2>/dev/null | grep -q 'ok installed' || egl+=("$pkg")
  done
  if [ ${#egl[@]} -gt 0 ] && have_gpu; then egl=(); fi  # the NVIDIA driver brings its EGL
  local want_mesa=0
  if ! have_gpu && ! lavapipe_ok; then want_mesa=1; fi
  if [ ${#need[@]} -eq 0 ] && [ $want_mesa = 0 ] && [ ${#egl[@]} -eq 0 ]; then log "system packages present"; return 0; fi
  if [ $want_mesa = 1 ]; then
    add_backports_suite
  fi
  log "apt-get update"
  $SUDO apt-get update -qq
  if [ ${#need[@]} -gt 0 ]; then
    log "installing ${need[*]}"
    DEBIAN_FRONTEND=noninteractive $SUDO apt-get install -y -qq --no-install-recommends "${need[@]}" >/dev/null
  fi
  if [ $want_mesa = 1 ]; then
    local codename; codename=$(. /etc/os-release && echo "$VERSION_CODENAME")
    log "installing mesa-vulkan-drivers from ${codename}-backports"
    DEBIAN_FRONTEND=noninteractive $SUDO apt-get install -y -qq --no-install-recommends \
      -t "${codename}-backports" mesa-vulkan-drivers libvulkan1 >/dev/null
  fi
  if [ ${#egl[@]} -gt 0 ]; then
    # from the suite Mesa's Vulkan driver came from, so every Mesa package has one version
    local suite=()
    [ -f /etc/apt/sources.list.d/dvla-backports.sources ] && suite=(-t "$(. /etc/os-release && echo "$VERSION_CODENAME")-backports")
    log "installing ${egl[*]} (EGL for MuJoCo's offscreen rendering)"
    DEBIAN_FRONTEND=noninteractive $SUDO apt-get install -y -qq --no-install-recommends "${suite[@]}" "${egl[@]}" >/dev/null
  fi
}

slurm_packages() {
  # A real single-host Slurm cluster for tests/integration/test_slurm.py (the test writes its own
  # slurm.conf and munge key and starts its own daemons). Optional: without it that test skips.
  command -v apt-get >/dev/null 2>&1 || { log "no apt-get: the Slurm test will skip (it needs slurm-wlm and munge)"; return 0; }
  if command -v slurmctld >/dev/null 2>&1 && command -v slurmd >/dev/null 2>&1 && command -v sbatch >/dev/null 2>&1 \
     && command -v munged >/dev/null 2>&1; then
    log "slurm-wlm and munge present"; return 0
  fi
  # The packages' scripts start munged, slurmctld and slurmd through invoke-rc.d unless a policy
  # forbids it; nothing should run until a test starts it, so forbid it during the install.
  local policy=/usr/sbin/policy-rc.d added=0 rc=0
  if [ ! -e "$policy" ]; then
    printf '#!/bin/sh\nexit 101\n' | $SUDO tee "$policy" >/dev/null && $SUDO chmod 755 "$policy" && added=1
  fi
  log "installing slurm-wlm and munge"
  { $SUDO apt-get update -qq && DEBIAN_FRONTEND=noninteractive $SUDO apt-get install -y -qq --no-install-recommends \
      slurm-wlm munge >/dev/null; } || rc=$?
  [ $added = 0 ] || $SUDO rm -f "$policy"
  [ $rc = 0 ] || log "could not install slurm-wlm and munge (apt-get: $rc): the Slurm test will skip"
  return 0
}

# --- 2/3. Python packages ------------------------------------------------------------------
python_packages() {
  if ! $PY -c 'import torch' 2>/dev/null; then
    if have_gpu; then
      log "CUDA machine: installing the stock torch wheel"
      $PY -m pip install -q "torch>=2.4"
    else
      # The CPU wheel; set DVLA_TORCH_INDEX to a CPU-only index where the local file is absent.
      log "CPU machine: installing torch==2.13.0 (CPU build)"
      $PY -m pip install -q ${DVLA_TORCH_INDEX:+--index-url "$DVLA_TORCH_INDEX"} "torch==2.13.0"
    fi
  fi
  # Always (re)install this checkout, editable: cheap when everything is satisfied, and it
  # keeps the `dvla` script pointing at this clone rather than at an older one.
  log "installing dvla (editable) and its dependencies"
  $PY -m pip install -q -e ".[test]"
  drop_broken_torchvision
}

drop_broken_torchvision() {
  # A torchvision wheel built for another torch (robomimic, a LIBERO dependency, pulls the stock
  # one) fails on import, and transformers imports it whenever it is installed: the Hugging Face
  # policies (docs/policies.md) would not load. dvla uses no torchvision; remove a broken one.
  if $PY -c 'import importlib.util as u, sys; sys.exit(0 if u.find_spec("torchvision") else 1)' 2>/dev/null \
     && ! $PY -c 'import torchvision' >/dev/null 2>&1; then
    log "torchvision does not load with this torch (it would break transformers): uninstalling it"
    $PY -m pip uninstall -y -q torchvision
  fi
  return 0
}

libero_packages() {
  # The `libero` extra (hf-libero, robosuite, mujoco): a separate step with pip held to the torch
  # and numpy now installed, since hf-libero's dependencies would otherwise pull another torch.
  [ "${DVLA_SETUP_LIBERO:-1}" = 0 ] && { log "DVLA_SETUP_LIBERO=0: the libero extra is not installed (its tests skip)"; return 0; }
  if $PY -c 'import importlib.util as u, sys; sys.exit(not (u.find_spec("libero") and u.find_spec("robosuite")))' 2>/dev/null; then
    log "libero extra present"; return 0
  fi
  local pins; pins=$(mktemp)
  $PY -c 'import numpy, torch; print(f"torch=={torch.__version__}\nnumpy=={numpy.__version__}")' > "$pins"
  log "installing the libero extra (hf-libero, robosuite, mujoco) with $(tr '\n' ' ' < "$pins")held"
  $PY -m pip install -q -c "$pins" -e ".[libero]" || log "could not install the libero extra: LIBERO's tests will skip"
  rm -f "$pins"
  drop_broken_torchvision
}

case "${1:-all}" in
  system) system_packages ;;
  python) python_packages ;;
  libero) libero_packages ;;
  slurm) slurm_packages ;;
  all) system_packages; python_packages ;;
  # `make test`: everything the suite can use (without these, their tests skip with a reason)
  test) system_packages; python_packages; slurm_packages; libero_packages ;;
  *) echo "usage: $0 [all|system|python|libero|slurm|test]" >&2; exit 2 ;;
esac
