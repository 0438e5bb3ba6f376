"""The bench deployment: udev rules (parsed and evaluated), systemd units (systemd-analyze verify), install.sh."""

from __future__ import annotations

import fnmatch
import os
import re
import shutil
import subprocess
from pathlib import Path

import pytest
from tools import require

from mca.capture.config import load_config

REPO = Path(__file__).resolve().parents[1]
DEPLOY = REPO / "deploy"
INSTALL = DEPLOY / "install.sh"
RULES = DEPLOY / "udev" / "70-mca-camera.rules"
SYSTEM_UNITS = ("mca-tether@.service", "mca-watch.service")

# --- udev rules ---------------------------------------------------------------

# Keys udev(7) knows; "{}" marks keys that take an attribute or variable name.
MATCH_KEYS = {
    "ACTION",
    "DEVPATH",
    "KERNEL",
    "KERNELS",
    "NAME",
    "SYMLINK",
    "SUBSYSTEM",
    "SUBSYSTEMS",
    "DRIVER",
    "DRIVERS",
    "TAG",
    "TAGS",
    "TEST",
    "PROGRAM",
    "RESULT",
    "ATTR{}",
    "ATTRS{}",
    "ENV{}",
    "CONST{}",
    "SYSCTL{}",
}
ASSIGN_KEYS = {
    "NAME",
    "SYMLINK",
    "OWNER",
    "GROUP",
    "MODE",
    "TAG",
    "SECLABEL{}",
    "ATTR{}",
    "SYSCTL{}",
    "ENV{}",
    "RUN{}",
    "RUN",
    "LABEL",
    "GOTO",
    "IMPORT{}",
    "OPTIONS",
}
TOKEN = re.compile(r'\s*([A-Z_]+)(\{[^}]*\})?\s*(==|!=|\+=|-=|:=|=)\s*"([^"]*)"\s*(,|$)')


def parse_rule(line: str) -> list[tuple[str, str | None, str, str]]:
    """One rule line as (key, {attribute} or None, operator, value) tuples; AssertionError if malformed."""
    tokens, pos = [], 0
    while pos < len(line):
        match = TOKEN.match(line, pos)
        assert match, f"cannot parse udev rule at column {pos}: {line!r}"
        key, attr, op, value, _ = match.groups()
        tokens.append((key, attr[1:-1] if attr else None, op, value))
        pos = match.end()
    return tokens


def rule_lines(path: Path = RULES) -> list[str]:
    return [
        line.strip()
        for line in path.read_text(encoding="utf-8").splitlines()
        if line.strip() and not line.lstrip().startswith("#")
    ]


def _udev_glob(pattern: str, value: str) -> bool:
    return any(fnmatch.fnmatchcase(value, alt) for alt in pattern.split("|"))


def evaluate(device: dict[str, str], path: Path = RULES) -> dict[str, object]:
    """What the rules assign to `device` (keys like "SUBSYSTEM", "ATTR{idVendor}", "ENV{DEVTYPE}", "ACTION").

    A small model of udev: matches with == and != (globs, `|` alternatives),
    assignments collected in order, GOTO/LABEL followed, IMPORT ignored.
    """
    rules = [parse_rule(line) for line in rule_lines(path)]
    labels = {value: i for i, rule in enumerate(rules) for key, _, _, value in rule if key == "LABEL"}
    out: dict[str, object] = {"TAG": set(), "SYMLINK": [], "ENV": {}}
    i = 0
    while i < len(rules):
        rule, jump = rules[i], None
        matches = True
        for key, attr, op, value in rule:
            if op in ("==", "!="):
                name = f"{key}{{{attr}}}" if attr else key
                ok = _udev_glob(value, device.get(name, ""))
                if ok != (op == "=="):
                    matches = False
                    break
        if matches:
            for key, attr, op, value in rule:
                if op in ("==", "!=") or key in ("LABEL", "IMPORT"):
                    continue
                if key == "GOTO":
                    jump = labels[value]
                elif key == "TAG":
                    out["TAG"].add(value)  # type: ignore[union-attr]
                elif key == "SYMLINK":
                    out["SYMLINK"].append(value)  # type: ignore[union-attr]
                elif key == "ENV":
                    out["ENV"][attr] = value  # type: ignore[index]
                else:
                    out[key] = value
        i = jump if jump is not None else i + 1
    return out


def _usb_device(vendor: str, product: str, interfaces: str, action: str = "add") -> dict[str, str]:
    return {
        "ACTION": action,
        "SUBSYSTEM": "usb",
        "ENV{DEVTYPE}": "usb_device",
        "ATTR{idVendor}": vendor,
        "ATTR{idProduct}": product,
        "ENV{ID_USB_INTERFACES}": interfaces,
    }


def _serial(vendor: str, product: str) -> dict[str, str]:
    return {
        "ACTION": "add",
        "SUBSYSTEM": "tty",
        "SUBSYSTEMS": "usb",
        "ATTRS{idVendor}": vendor,
        "ATTRS{idProduct}": product,
        "KERNEL": "ttyUSB0",
    }


def test_every_udev_line_is_key_operator_value_pairs_with_known_keys() -> None:
    lines = rule_lines()
    assert len(lines) >= 8
    for line in lines:
        for key, attr, op, _ in parse_rule(line):
            name = key + ("{}" if attr is not None else "")
            if op in ("==", "!="):
                assert name in MATCH_KEYS, f"{name} is not a udev match key: {line}"
            else:
                assert name in ASSIGN_KEYS, f"{name} is not a udev assignment key: {line}"
            if key == "MODE":
                assert re.fullmatch(r"0[0-7]{3}", _), line
    labels = [v for line in lines for k, _, _, v in parse_rule(line) if k == "LABEL"]
    gotos = [v for line in lines for k, _, _, v in parse_rule(line) if k == "GOTO"]
    assert len(labels) == len(set(labels))
    assert set(gotos) <= set(labels), "every GOTO needs its LABEL"


def test_every_udev_rule_is_explained_by_a_comment() -> None:
    previous = ""
    for raw in RULES.read_text(encoding="utf-8").splitlines():
        line = raw.strip()
        if line and not line.startswith("#") and not line.startswith("LABEL="):
            assert previous.startswith("#") or previous.startswith("LABEL="), f"no comment above: {line}"
        if line:
            previous = line


def test_canon_70d_gets_plugdev_uaccess_and_a_name() -> None:
    result = evaluate(_usb_device("04a9", "3253", ":060101:"))
    assert result["GROUP"] == "plugdev" and result["MODE"] == "0660"
    assert "uaccess" in result["TAG"]  # type: ignore[operator]
    assert "mca-camera" in result["SYMLINK"]  # type: ignore[operator]
    assert result["ENV"]["ID_MCA_CAMERA"] == "eos70d"  # type: ignore[index]
    # Matched by id even if the interface list were not known.
    assert evaluate(_usb_device("04a9", "3253", ""))["GROUP"] == "plugdev"


def test_any_ptp_interface_gets_plugdev() -> None:
    nikon = evaluate(_usb_device("04b0", "0429", ":060101:"))
    assert nikon["GROUP"] == "plugdev" and "uaccess" in nikon["TAG"]  # type: ignore[operator]
    assert nikon["SYMLINK"] == []
    other_canon = evaluate(_usb_device("04a9", "3218", ":060101:ff0000:"))
    assert other_canon["GROUP"] == "plugdev" and other_canon["ENV"]["ID_MCA_CAMERA"] == "canon"  # type: ignore[index]


@pytest.mark.parametrize(
    "device",
    [
        _usb_device("046d", "c52b", ":030101:030102:"),  # a keyboard receiver
        _usb_device("04a9", "1769", ":070102:ff0000:"),  # a Canon printer, no PTP interface
        _usb_device("04a9", "3253", ":060101:", action="remove"),
        {"ACTION": "add", "SUBSYSTEM": "usb", "ENV{DEVTYPE}": "usb_interface", "ENV{ID_USB_INTERFACES}": ":060101:"},
        {"ACTION": "add", "SUBSYSTEM": "block", "KERNEL": "sda"},
    ],
)
def test_other_devices_are_left_alone(device: dict[str, str]) -> None:
    result = evaluate(device)
    assert "GROUP" not in result and "MODE" not in result and not result["TAG"] and not result["SYMLINK"]


@pytest.mark.parametrize("vendor, product", [("1a86", "7523"), ("0403", "6001"), ("2341", "0043"), ("10c4", "ea60")])
def test_grbl_serial_boards_get_dialout_and_mca_rail(vendor: str, product: str) -> None:
    result = evaluate(_serial(vendor, product))
    assert result["GROUP"] == "dialout" and result["MODE"] == "0660"
    assert result["SYMLINK"] == ["mca-rail"]
    assert result["ENV"]["ID_MM_DEVICE_IGNORE"] == "1"  # type: ignore[index]


def test_unknown_serial_adaptor_is_left_alone() -> None:
    result = evaluate(_serial("067b", "2303"))
    assert "GROUP" not in result and not result["SYMLINK"]


# --- install.sh ---------------------------------------------------------------


def run_install(*args: str, home: Path, check: bool = True) -> subprocess.CompletedProcess[str]:
    env = {k: v for k, v in os.environ.items() if not k.startswith("XDG_") and k != "MCA_CONFIG"}
    env["HOME"] = str(home)
    result = subprocess.run(["bash", str(INSTALL), *args], capture_output=True, text=True, env=env, timeout=60)
    if check:
        assert result.returncode == 0, result.stdout + result.stderr
    return result


def _files_under(path: Path) -> list[Path]:
    return sorted(p for p in path.rglob("*")) if path.exists() else []


def test_install_sh_syntax() -> None:
    subprocess.run(["bash", "-n", str(INSTALL)], check=True)
    text = INSTALL.read_text(encoding="utf-8")
    assert "set -euo pipefail" in text
    assert os.access(INSTALL, os.X_OK), "install.sh should be executable"


def test_install_sh_is_shellcheck_clean() -> None:
    require("shellcheck", "apt-get install shellcheck")
    result = subprocess.run(["shellcheck", str(INSTALL)], capture_output=True, text=True)
    assert result.returncode == 0, result.stdout


def test_dry_run_system_install_lists_every_step_and_changes_nothing(tmp_path: Path) -> None:
    prefix = tmp_path / "prefix"
    out = run_install("--dry-run", "--prefix", str(prefix), home=tmp_path / "home").stdout
    lines = out.splitlines()
    assert f"+ python3 -m venv {prefix}/venv" in lines
    assert any(line.startswith(f"+ {prefix}/venv/bin/python -m pip install --upgrade {REPO}") for line in lines)
    assert any(
        re.match(r"\+ (useradd --system .*--groups plugdev\\?,dialout .* mca|usermod .*plugdev.* mca)$", line)
        for line in lines
    ), out
    assert "+ install -d -o mca -g mca -m 0750 /var/lib/mca /var/lib/mca/raw /var/lib/mca/processed" in lines
    for source, dest in [
        ("udev/70-mca-camera.rules", "/etc/udev/rules.d/70-mca-camera.rules"),
        ("systemd/mca-tether@.service", "/etc/systemd/system/mca-tether@.service"),
        ("systemd/mca-watch.service", "/etc/systemd/system/mca-watch.service"),
        ("config.example.toml", "/etc/mca/config.toml"),
    ]:
        if Path(dest).exists():
            continue  # this machine has it already: install.sh keeps or compares it
        assert any(line.startswith(f"+ render {DEPLOY / source} -> {dest} ") for line in lines), (dest, out)
    assert f"prefix {prefix}" in out
    assert not prefix.exists() and not (tmp_path / "home").exists()


def test_dry_run_user_only_stays_in_home(tmp_path: Path) -> None:
    home = tmp_path / "home"
    out = run_install("--user-only", "--dry-run", home=home).stdout
    lines = out.splitlines()
    assert f"+ python3 -m venv {home}/.local/share/mca/venv" in lines
    for name in SYSTEM_UNITS:
        assert any(
            line.startswith(f"+ render {DEPLOY / 'systemd' / 'user' / name} -> {home}/.config/systemd/user/{name} ")
            for line in lines
        ), out
    assert any(
        line.startswith(f"+ render {DEPLOY / 'config.example.toml'} -> {home}/.config/mca/config.toml ")
        for line in lines
    )
    assert "+ systemctl --user daemon-reload" in lines
    commands = [line for line in lines if line.startswith("+ ")]
    assert not any(re.search(r"useradd|usermod|groupadd|udevadm|-> /etc/", line) for line in commands), commands
    assert all(str(home) in line for line in commands if "render" in line or "mkdir" in line)
    assert not home.exists()


def test_dry_run_honours_prefix_and_data_dir(tmp_path: Path) -> None:
    out = run_install(
        "--user-only",
        "--dry-run",
        "--prefix",
        str(tmp_path / "p"),
        "--data-dir",
        str(tmp_path / "d"),
        home=tmp_path / "home",
    ).stdout
    assert f"+ python3 -m venv {tmp_path}/p/venv" in out.splitlines()
    assert f"+ mkdir -p {tmp_path}/d/raw" in out.splitlines()


def test_bad_options_are_refused(tmp_path: Path) -> None:
    result = run_install("--frobnicate", home=tmp_path, check=False)
    assert result.returncode == 2 and "unknown option '--frobnicate'" in result.stderr
    result = run_install("--prefix", home=tmp_path, check=False)
    assert result.returncode == 2 and "--prefix needs a value" in result.stderr


def test_system_install_without_root_is_refused(tmp_path: Path) -> None:
    command = ["bash", str(INSTALL), "--no-venv"]
    if os.geteuid() == 0:
        if shutil.which("setpriv") is None:
            pytest.skip("running as root without setpriv: cannot drop to an unprivileged user")
        command = ["setpriv", "--reuid=65534", "--regid=65534", "--clear-groups", *command]
    result = subprocess.run(
        command,
        capture_output=True,
        text=True,
        timeout=60,
        env={"PATH": os.environ.get("PATH", "/usr/bin:/bin"), "HOME": str(tmp_path)},
    )
    assert result.returncode == 2, result.stdout + result.stderr
    assert "needs root" in result.stderr and "--user-only" in result.stderr


def test_user_only_install_writes_files_and_is_idempotent(tmp_path: Path) -> None:
    home = tmp_path / "home"
    out = run_install("--user-only", "--no-venv", home=home).stdout
    units = home / ".config" / "systemd" / "user"
    config = home / ".config" / "mca"
    for name in SYSTEM_UNITS:
        text = (units / name).read_text(encoding="utf-8")
        assert f"ExecStart={home}/.local/share/mca/venv/bin/mca " in text
        assert "%h/" not in text.split("[Service]")[1].split("ExecStart")[0].replace("%h/mca", "")
    assert f"MCA_WATCH_DIR={home}/mca/raw" in (units / "mca-watch.service").read_text(encoding="utf-8")
    assert (home / "mca" / "raw").is_dir() and (home / "mca" / "processed").is_dir()
    assert {p.name for p in config.iterdir()} == {"config.toml", "tether.env", "watch.env"}
    loaded = load_config(env={"MCA_CONFIG": str(config / "config.toml")})
    assert loaded.output_dir == home / "mca" and loaded.source_of("output_dir") == str(config / "config.toml")
    assert "wrote" in out

    # An edited config survives a second run; unchanged units are not rewritten.
    (config / "config.toml").write_text('camera = "sim"\n', encoding="utf-8")
    before = {p: p.stat().st_mtime_ns for p in _files_under(units)}
    again = run_install("--user-only", "--no-venv", home=home).stdout
    assert (config / "config.toml").read_text(encoding="utf-8") == 'camera = "sim"\n'
    assert f"keep {config}/config.toml" in again
    assert again.count("unchanged") == len(SYSTEM_UNITS)
    assert before == {p: p.stat().st_mtime_ns for p in _files_under(units)}


def test_destdir_stages_the_system_install(tmp_path: Path) -> None:
    root, prefix, data = tmp_path / "root", tmp_path / "opt", tmp_path / "data"
    run_install("--destdir", str(root), "--prefix", str(prefix), "--data-dir", str(data), home=tmp_path)
    rules = root / "etc/udev/rules.d/70-mca-camera.rules"
    assert rules.read_text(encoding="utf-8") == RULES.read_text(encoding="utf-8")
    for name in SYSTEM_UNITS:
        text = (root / "etc/systemd/system" / name).read_text(encoding="utf-8")
        assert "/opt/mca" not in text and "/var/lib/mca" not in text
        assert f"ExecStart={prefix}/venv/bin/mca " in text
        assert f"ReadWritePaths={data}\n" in text
    assert load_config(env={"MCA_CONFIG": str(root / "etc/mca/config.toml")}).output_dir == data


# --- systemd units ------------------------------------------------------------


def unit_settings(path: Path) -> dict[str, list[str]]:
    settings: dict[str, list[str]] = {}
    for line in path.read_text(encoding="utf-8").splitlines():
        if "=" in line and not line.startswith(("#", ";", "[")):
            key, _, value = line.partition("=")
            settings.setdefault(key.strip(), []).append(value.strip())
    return settings


@pytest.mark.parametrize("name", SYSTEM_UNITS)
def test_system_units_are_hardened_and_unprivileged(name: str) -> None:
    s = unit_settings(DEPLOY / "systemd" / name)
    assert s["User"] == ["mca"] and "DynamicUser" not in s
    for key, value in [
        ("NoNewPrivileges", "yes"),
        ("ProtectSystem", "strict"),
        ("PrivateTmp", "yes"),
        ("ProtectHome", "read-only"),
        ("ReadWritePaths", "/var/lib/mca"),
        ("Restart", "on-failure"),
    ]:
        assert s[key] == [value], key
    assert s["ExecStart"][0].startswith("/opt/mca/venv/bin/mca ")
    assert s["CapabilityBoundingSet"] == [""]


def test_tether_unit_reaches_camera_and_rail_and_names_its_folder() -> None:
    s = unit_settings(DEPLOY / "systemd" / "mca-tether@.service")
    assert s["DevicePolicy"] == ["closed"]
    assert {"char-usb_device rw", "char-ttyUSB rw", "char-ttyACM rw"} <= set(s["DeviceAllow"])
    assert s["SupplementaryGroups"] == ["plugdev dialout"]
    assert "MCA_OUT=/var/lib/mca/raw/%i" in s["Environment"]
    assert s["ExecStart"] == ["/opt/mca/venv/bin/mca capture --tethered --out ${MCA_OUT} $MCA_TETHER_ARGS"]
    assert "AF_NETLINK" in s["RestrictAddressFamilies"][0]  # libusb hotplug


def test_watch_unit_runs_the_watcher_without_devices() -> None:
    s = unit_settings(DEPLOY / "systemd" / "mca-watch.service")
    assert s["PrivateDevices"] == ["yes"] and "DeviceAllow" not in s
    assert s["ExecStart"][0].startswith(
        "/opt/mca/venv/bin/mca process ${MCA_WATCH_DIR} --watch --out ${MCA_PROCESSED_DIR} --workers ${MCA_WORKERS}"
    )


SYSTEMD_ANALYZE = shutil.which("systemd-analyze")
needs_systemd_analyze = pytest.mark.skipif(  # on CI (CI set) a missing systemd-analyze fails instead
    SYSTEMD_ANALYZE is None and not os.environ.get("CI"),
    reason="systemd-analyze not installed (Debian: apt-get install systemd)",
)


def _fake_mca(prefix: Path) -> None:
    binary = prefix / "venv" / "bin" / "mca"
    binary.parent.mkdir(parents=True)
    binary.write_text("#!/bin/sh\nexit 0\n", encoding="utf-8")
    binary.chmod(0o755)


def verify(unit_dir: Path, names: list[str], user: bool, runtime: Path) -> subprocess.CompletedProcess[str]:
    env = dict(os.environ, XDG_RUNTIME_DIR=str(runtime), SYSTEMD_LOG_COLOR="0")
    runtime.mkdir(mode=0o700, exist_ok=True)
    args = [SYSTEMD_ANALYZE or "systemd-analyze"] + (["--user"] if user else []) + ["verify"]
    return subprocess.run(
        args + [str(unit_dir / n) for n in names], capture_output=True, text=True, env=env, cwd=unit_dir, timeout=60
    )


def _complaints(result: subprocess.CompletedProcess[str], names: list[str]) -> list[str]:
    """Lines of verify's output about our units (it can also grumble about the host's own units)."""
    stems = {n.split("@")[0].removesuffix(".service") for n in names}
    return [line for line in (result.stdout + result.stderr).splitlines() if any(s in line for s in stems)]


@needs_systemd_analyze
def test_systemd_analyze_verifies_the_installed_system_units(tmp_path: Path) -> None:
    root, prefix = tmp_path / "root", tmp_path / "opt"
    run_install("--destdir", str(root), "--prefix", str(prefix), "--data-dir", str(tmp_path / "data"), home=tmp_path)
    _fake_mca(prefix)
    names = ["mca-watch.service", "mca-tether@bench.service"]
    result = verify(root / "etc/systemd/system", names, user=False, runtime=tmp_path / "run")
    assert result.returncode == 0 and not _complaints(result, names), result.stdout + result.stderr


@needs_systemd_analyze
def test_systemd_analyze_verifies_the_installed_user_units(tmp_path: Path) -> None:
    home = tmp_path / "home"
    run_install("--user-only", "--no-venv", home=home)
    _fake_mca(home / ".local/share/mca")
    names = ["mca-watch.service", "mca-tether@bench.service"]
    result = verify(home / ".config/systemd/user", names, user=True, runtime=tmp_path / "run")
    if result.returncode != 0 and "Failed to initialize manager" in result.stderr:
        pytest.skip(f"systemd-analyze --user cannot start here: {result.stderr.strip()}")
    assert result.returncode == 0 and not _complaints(result, names), result.stdout + result.stderr


@needs_systemd_analyze
def test_systemd_analyze_catches_a_missing_binary(tmp_path: Path) -> None:
    """The check above is not vacuous: without the venv's mca, verify fails."""
    root = tmp_path / "root"
    run_install("--destdir", str(root), "--prefix", str(tmp_path / "nowhere"), home=tmp_path)
    result = verify(root / "etc/systemd/system", ["mca-watch.service"], user=False, runtime=tmp_path / "run")
    assert result.returncode != 0
    assert f"{tmp_path}/nowhere/venv/bin/mca" in result.stdout + result.stderr


@pytest.mark.parametrize("name", SYSTEM_UNITS + tuple(f"user/{n}" for n in SYSTEM_UNITS))
def test_exec_start_is_a_command_line_mca_accepts(name: str, tmp_path: Path) -> None:
    """ExecStart's options exist in the real `mca` (unknown options fail before --help is honoured)."""
    import sys

    s = unit_settings(DEPLOY / "systemd" / name)
    env = dict(entry.split("=", 1) for entry in s["Environment"])
    words = s["ExecStart"][0].split()
    args = []
    for word in words[1:]:
        if word.startswith("$") and not word.startswith("${"):
            continue  # $MCA_*_ARGS: empty by default, split into words by systemd
        args.append(
            re.sub(r"\$\{(\w+)\}", lambda m: env[m.group(1)], word).replace("%i", "bench").replace("%h", str(tmp_path))
        )
    assert words[0].endswith("/venv/bin/mca")
    result = subprocess.run(
        [sys.executable, "-m", "mca", *args, "--help"], capture_output=True, text=True, timeout=120, cwd=tmp_path
    )
    assert result.returncode == 0, f"{args}: {result.stdout}{result.stderr}"
