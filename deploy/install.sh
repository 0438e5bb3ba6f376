#!/usr/bin/env bash
# Install the MCA appliance on a bench machine: virtual environment, service user,
# data folder, udev rules, systemd units and a default config. Safe to run again.
set -euo pipefail

usage() {
    cat <<'EOF'
Usage: deploy/install.sh [OPTIONS]

System install (as root): venv in PREFIX/venv, system user `mca` in plugdev and
dialout, data folder, /etc/udev/rules.d/70-mca-camera.rules, units in
/etc/systemd/system, config in /etc/mca. Services are installed, not enabled.

  --prefix DIR     where the venv goes (default /opt/mca; with --user-only
                   ${XDG_DATA_HOME:-~/.local/share}/mca)
  --data-dir DIR   data folder for raw photos and results (default /var/lib/mca;
                   with --user-only ~/mca)
  --user-only      no root: venv, user units in ~/.config/systemd/user, config
                   in ~/.config/mca; udev rules and groups are left to an admin
  --dry-run        print what would be done, change nothing
  --destdir DIR    stage every file under DIR (for packaging and tests): no venv,
                   no user accounts, no udevadm or systemctl
  --source DIR     project checkout to install (default: this script's repo)
  --extras LIST    pip extras to install (default: usb; "" for none)
  --python EXE     interpreter for the venv (default: python3, >= 3.11)
  --no-venv        skip the virtual environment
  -h, --help       this text
EOF
}

die() {
    printf 'install.sh: error: %s\n' "$*" >&2
    exit 2
}

say() {
    printf '%s\n' "$*"
}

SCRIPT_DIR=$(cd -- "$(dirname -- "${BASH_SOURCE[0]}")" && pwd)
SOURCE_DIR=$(dirname -- "$SCRIPT_DIR")
DRY_RUN=0
USER_ONLY=0
NO_VENV=0
PREFIX=""
DATA_DIR=""
DESTDIR=""
EXTRAS="usb"
PYTHON=${PYTHON:-python3}
SERVICE_USER=mca

need_value() {
    [[ $# -ge 2 && -n $2 ]] || die "$1 needs a value (see --help)"
}

while [[ $# -gt 0 ]]; do
    case $1 in
        --prefix) need_value "$@"; PREFIX=$2; shift 2 ;;
        --prefix=*) PREFIX=${1#*=}; shift ;;
        --data-dir) need_value "$@"; DATA_DIR=$2; shift 2 ;;
        --data-dir=*) DATA_DIR=${1#*=}; shift ;;
        --destdir) need_value "$@"; DESTDIR=$2; shift 2 ;;
        --destdir=*) DESTDIR=${1#*=}; shift ;;
        --source) need_value "$@"; SOURCE_DIR=$2; shift 2 ;;
        --source=*) SOURCE_DIR=${1#*=}; shift ;;
        --extras) [[ $# -ge 2 ]] || die "--extras needs a value"; EXTRAS=$2; shift 2 ;;
        --extras=*) EXTRAS=${1#*=}; shift ;;
        --python) need_value "$@"; PYTHON=$2; shift 2 ;;
        --python=*) PYTHON=${1#*=}; shift ;;
        --user-only) USER_ONLY=1; shift ;;
        --dry-run) DRY_RUN=1; shift ;;
        --no-venv) NO_VENV=1; shift ;;
        -h|--help) usage; exit 0 ;;
        *) usage >&2; die "unknown option '$1'" ;;
    esac
done

absolute() {
    # An absolute path without requiring it to exist.
    case $1 in
        /*) printf '%s' "$1" ;;
        *) printf '%s/%s' "$PWD" "$1" ;;
    esac
}

CONFIG_HOME=${XDG_CONFIG_HOME:-$HOME/.config}
if [[ $USER_ONLY -eq 1 ]]; then
    PREFIX=${PREFIX:-${XDG_DATA_HOME:-$HOME/.local/share}/mca}
    DATA_DIR=${DATA_DIR:-$HOME/mca}
    CONFIG_DIR=$CONFIG_HOME/mca
    UNIT_SRC=$SCRIPT_DIR/systemd/user
    UNIT_DIR=$CONFIG_HOME/systemd/user
    # The user units name these defaults with systemd specifiers.
    UNIT_PREFIX_DEFAULT='%h/.local/share/mca'
    UNIT_DATA_DEFAULT='%h/mca'
else
    PREFIX=${PREFIX:-/opt/mca}
    DATA_DIR=${DATA_DIR:-/var/lib/mca}
    CONFIG_DIR=/etc/mca
    UNIT_SRC=$SCRIPT_DIR/systemd
    UNIT_DIR=/etc/systemd/system
    UNIT_PREFIX_DEFAULT=/opt/mca
    UNIT_DATA_DEFAULT=/var/lib/mca
fi
PREFIX=$(absolute "$PREFIX")
DATA_DIR=$(absolute "$DATA_DIR")
SOURCE_DIR=$(absolute "$SOURCE_DIR")
[[ -z $DESTDIR ]] || DESTDIR=$(absolute "$DESTDIR")
UDEV_RULES=/etc/udev/rules.d/70-mca-camera.rules
VENV=$PREFIX/venv
[[ -n $DESTDIR ]] && NO_VENV=1

[[ -f $SOURCE_DIR/pyproject.toml ]] || die "$SOURCE_DIR is not the project checkout (no pyproject.toml); pass --source"
[[ -f $SCRIPT_DIR/udev/70-mca-camera.rules ]] || die "$SCRIPT_DIR/udev/70-mca-camera.rules is missing: incomplete checkout?"

if [[ $USER_ONLY -eq 0 && $DRY_RUN -eq 0 && -z $DESTDIR && $EUID -ne 0 ]]; then
    die "a system install needs root: run it with sudo, or use --user-only (or --dry-run to look first)"
fi

# --- Helpers: every change goes through `run` or `write_file`, which honour --dry-run.

run() {
    if [[ $DRY_RUN -eq 1 ]]; then
        printf '+'
        printf ' %q' "$@"
        printf '\n'
    else
        "$@"
    fi
}

# A path as written on this machine: under DESTDIR when staging.
staged() {
    printf '%s%s' "$DESTDIR" "$1"
}

sed_escape() {
    # Escape a string for the replacement side of a sed s||| command.
    printf '%s' "$1" | sed -e 's/[\\|&]/\\&/g'
}

# render SRC DEST MODE [KEEP]: copy SRC to DEST with the default prefix and data
# folder replaced; KEEP=keep leaves an existing DEST alone (config someone edited).
render() {
    local src=$1 dest=$2 mode=$3 keep=${4:-}
    local target tmp
    target=$(staged "$dest")
    if [[ $keep == keep && -e $target ]]; then
        say "keep $dest (exists; compare with $src)"
        return 0
    fi
    if [[ $DRY_RUN -eq 1 ]]; then
        say "+ render $src -> $target (prefix $PREFIX, data $DATA_DIR, mode $mode)"
        return 0
    fi
    tmp=$(mktemp)
    # Defaults become tokens first, so a new value that contains another default is left alone.
    sed -e "s|$(sed_escape "$UNIT_PREFIX_DEFAULT")|@MCA_PREFIX@|g" \
        -e "s|$(sed_escape "$UNIT_DATA_DEFAULT")|@MCA_DATA@|g" \
        -e "s|/opt/mca|@MCA_PREFIX@|g" -e "s|/var/lib/mca|@MCA_DATA@|g" \
        -e "s|@MCA_PREFIX@|$(sed_escape "$PREFIX")|g" -e "s|@MCA_DATA@|$(sed_escape "$DATA_DIR")|g" \
        "$src" >"$tmp"
    if [[ -e $target ]] && cmp -s "$tmp" "$target"; then
        say "unchanged $target"
        rm -f "$tmp"
        return 0
    fi
    install -D -m "$mode" "$tmp" "$target"
    rm -f "$tmp"
    say "wrote $target"
}

# config_file DEST: the example config with output_dir pointing at the data folder.
config_file() {
    local dest=$1 target tmp
    target=$(staged "$dest")
    if [[ -e $target ]]; then
        say "keep $dest (exists; compare with $SCRIPT_DIR/config.example.toml)"
        return 0
    fi
    if [[ $DRY_RUN -eq 1 ]]; then
        say "+ render $SCRIPT_DIR/config.example.toml -> $target (output_dir = \"$DATA_DIR\", mode 0644)"
        return 0
    fi
    tmp=$(mktemp)
    sed -e "s|^output_dir = .*|output_dir = \"$(sed_escape "$DATA_DIR")\"|" "$SCRIPT_DIR/config.example.toml" >"$tmp"
    install -D -m 0644 "$tmp" "$target"
    rm -f "$tmp"
    say "wrote $target"
}

have() {
    command -v "$1" >/dev/null 2>&1
}

# --- Steps

step_venv() {
    if [[ $NO_VENV -eq 1 ]]; then
        say "skip virtual environment${DESTDIR:+ (--destdir stages files only)}"
        return 0
    fi
    if [[ $DRY_RUN -eq 0 ]]; then
        have "$PYTHON" || die "$PYTHON not found: install Python >= 3.11 (apt-get install python3 python3-venv) or pass --python"
        "$PYTHON" -c 'import sys; sys.exit(sys.version_info < (3, 11))' \
            || die "$PYTHON is older than 3.11; pass --python with a newer interpreter"
    fi
    if [[ -x $VENV/bin/python ]]; then
        say "venv $VENV exists: upgrading the project in it"
    else
        run mkdir -p "$PREFIX"
        run "$PYTHON" -m venv "$VENV"
    fi
    local spec=$SOURCE_DIR
    [[ -z $EXTRAS ]] || spec="${SOURCE_DIR}[${EXTRAS}]"
    run "$VENV/bin/python" -m pip install --upgrade "$spec"
}

step_user() {
    if [[ -n $DESTDIR ]]; then
        say "skip system user $SERVICE_USER and groups (--destdir)"
        return 0
    fi
    local group
    for group in plugdev dialout; do
        if getent group "$group" >/dev/null; then
            say "group $group exists"
        else
            run groupadd --system "$group"
        fi
    done
    if id -u "$SERVICE_USER" >/dev/null 2>&1; then
        say "user $SERVICE_USER exists: making sure it is in plugdev and dialout"
        run usermod --append --groups plugdev,dialout "$SERVICE_USER"
    else
        # Its own group, reusing one left behind by an earlier install.
        local own_group=(--user-group)
        if getent group "$SERVICE_USER" >/dev/null; then
            own_group=(--gid "$SERVICE_USER")
        fi
        run useradd --system "${own_group[@]}" --groups plugdev,dialout --home-dir "$DATA_DIR" \
            --no-create-home --shell /usr/sbin/nologin --comment "MCA bench appliance" "$SERVICE_USER"
    fi
}

step_data_dir() {
    local dir
    if [[ $USER_ONLY -eq 1 || -n $DESTDIR ]]; then
        for dir in "$DATA_DIR" "$DATA_DIR/raw" "$DATA_DIR/processed"; do
            run mkdir -p "$(staged "$dir")"
        done
    else
        run install -d -o "$SERVICE_USER" -g "$SERVICE_USER" -m 0750 \
            "$DATA_DIR" "$DATA_DIR/raw" "$DATA_DIR/processed"
    fi
}

step_config() {
    run mkdir -p "$(staged "$CONFIG_DIR")"
    config_file "$CONFIG_DIR/config.toml"
    render "$SCRIPT_DIR/systemd/tether.env" "$CONFIG_DIR/tether.env" 0644 keep
    render "$SCRIPT_DIR/systemd/watch.env" "$CONFIG_DIR/watch.env" 0644 keep
}

step_udev() {
    if [[ $USER_ONLY -eq 1 ]]; then
        if [[ -e $UDEV_RULES ]]; then
            say "udev rules $UDEV_RULES are installed"
        else
            say "note: no $UDEV_RULES yet; ask an admin to run:"
            say "  sudo install -m 0644 $SCRIPT_DIR/udev/70-mca-camera.rules $UDEV_RULES"
            say "  sudo udevadm control --reload-rules && sudo udevadm trigger"
        fi
        if ! id -nG 2>/dev/null | tr ' ' '\n' | grep -qx plugdev; then
            say "note: $(id -un) is not in plugdev; without a desktop seat (uaccess) the camera stays root-only:"
            say "  sudo usermod -aG plugdev,dialout $(id -un)   # then log in again"
        fi
        return 0
    fi
    render "$SCRIPT_DIR/udev/70-mca-camera.rules" "$UDEV_RULES" 0644
    if [[ -n $DESTDIR ]]; then
        say "skip udevadm (--destdir)"
    elif have udevadm && [[ -S /run/udev/control || $DRY_RUN -eq 1 ]]; then
        run udevadm control --reload-rules
        run udevadm trigger --action=change --subsystem-match=usb --subsystem-match=tty
    else
        say "note: udev is not running here; the rules apply from the next boot or udev start"
    fi
}

step_units() {
    local src
    for src in "$UNIT_SRC"/*.service; do
        render "$src" "$UNIT_DIR/$(basename -- "$src")" 0644
    done
    if [[ -n $DESTDIR ]]; then
        say "skip systemctl daemon-reload (--destdir)"
    elif [[ $USER_ONLY -eq 1 ]]; then
        if [[ $DRY_RUN -eq 1 ]] || systemctl --user show-environment >/dev/null 2>&1; then
            run systemctl --user daemon-reload
        else
            say "note: no systemd user manager reachable; run 'systemctl --user daemon-reload' after logging in"
        fi
    elif [[ -d /run/systemd/system ]]; then
        run systemctl daemon-reload
    else
        say "note: systemd is not running here; the units load at the next boot"
    fi
}

step_hints() {
    local ctl="systemctl" cfg="$CONFIG_DIR"
    [[ $USER_ONLY -eq 0 ]] || ctl="systemctl --user"
    say ""
    say "Installed (not enabled). Next:"
    say "  edit $cfg/tether.env and $cfg/watch.env (camera, profile, workers for the services)"
    say "  edit $cfg/config.toml (appliance defaults; check: $VENV/bin/mca config show)"
    say "  $ctl enable --now mca-watch.service"
    say "  $ctl start mca-tether@bench.service     # writes into $DATA_DIR/raw/bench"
    say "On a desktop, stop gvfs from claiming the camera (see deploy/README.md):"
    say "  systemctl --user mask --now gvfs-gphoto2-volume-monitor.service"
}

if [[ $DRY_RUN -eq 1 ]]; then
    say "dry run: nothing is changed"
fi
if [[ $USER_ONLY -eq 1 ]]; then
    say "user install for $(id -un): prefix $PREFIX, data $DATA_DIR, config $CONFIG_DIR, units $UNIT_DIR"
else
    say "system install: prefix $PREFIX, data $DATA_DIR, config $CONFIG_DIR, units $UNIT_DIR, user $SERVICE_USER"
fi
[[ -z $DESTDIR ]] || say "staging under $DESTDIR"

step_venv
[[ $USER_ONLY -eq 1 ]] || step_user
step_data_dir
step_config
step_udev
step_units
step_hints
