"""The site's authority and host certificates (common/certs.py) and ``voxelwatch certs``.

The certificates are read back with ``cryptography`` and checked against the
authority with ``openssl verify`` where the command exists; that they work
in zenoh is for tests/test_access.py.
"""

from __future__ import annotations

import ipaddress
import shutil
import stat
import subprocess

import pytest
from cryptography import x509
from cryptography.x509.oid import ExtendedKeyUsageOID, NameOID

from common.certs import CertError, common_name, make_site_certs, read_common_name
from voxelwatch.cli import main as cli_main
from tests.tinysite import write_site


def _sans(path) -> set[str]:
    cert = x509.load_pem_x509_certificate(path.read_bytes())
    alt = cert.extensions.get_extension_for_class(x509.SubjectAlternativeName).value
    return {*alt.get_values_for_type(x509.DNSName), *(str(a) for a in alt.get_values_for_type(x509.IPAddress))}


def test_one_certificate_per_host_signed_by_the_site_authority(tmp_path):
    made = make_site_certs(tmp_path / "c", site="flat", cameras=["cam1", "cam2"], readers=["reader", "tablet"],
                           names={"router": ["fusion.local"], "cam1": ["192.168.1.21"]})
    files = sorted(p.name for p in (tmp_path / "c").iterdir())
    assert files == sorted(["ca.pem", "ca-key.pem"] + [f"{h}{s}" for h in ("router", "fusion", "cam1", "cam2", "reader", "tablet")
                                                        for s in (".pem", "-key.pem")])
    ca = x509.load_pem_x509_certificate(made.ca.read_bytes())
    assert ca.extensions.get_extension_for_class(x509.BasicConstraints).value.ca
    cns = {h.host: read_common_name(h.cert) for h in made.hosts}
    assert cns == {"router": "router", "fusion": "fusion", "cam1": "camera-cam1", "cam2": "camera-cam2",
                   "reader": "reader-reader", "tablet": "reader-tablet"}
    for h in made.hosts:
        cert = x509.load_pem_x509_certificate(h.cert.read_bytes())
        assert cert.issuer == ca.subject
        cert.verify_directly_issued_by(ca)
        usage = cert.extensions.get_extension_for_class(x509.ExtendedKeyUsage).value
        assert {ExtendedKeyUsageOID.SERVER_AUTH, ExtendedKeyUsageOID.CLIENT_AUTH} <= set(usage)
        assert {"localhost", "127.0.0.1"} <= _sans(h.cert)
        assert stat.S_IMODE(h.key.stat().st_mode) == 0o600, h.key
    assert stat.S_IMODE(made.ca_key.stat().st_mode) == 0o600
    assert "fusion.local" in _sans(made.folder / "router.pem") and "fusion.local" not in _sans(made.folder / "cam2.pem")
    assert "192.168.1.21" in _sans(made.folder / "cam1.pem")
    # an address goes in as an IP entry, not a DNS name
    cert = x509.load_pem_x509_certificate((made.folder / "cam1.pem").read_bytes())
    alt = cert.extensions.get_extension_for_class(x509.SubjectAlternativeName).value
    assert ipaddress.ip_address("192.168.1.21") in alt.get_values_for_type(x509.IPAddress)
    assert cert.subject.get_attributes_for_oid(NameOID.COMMON_NAME)[0].value == "camera-cam1"


@pytest.mark.skipif(shutil.which("openssl") is None, reason="no openssl command")
def test_openssl_verifies_every_host_certificate_against_the_authority(tmp_path):
    made = make_site_certs(tmp_path, site="flat", cameras=["cam1"])
    for h in made.hosts:
        out = subprocess.run(["openssl", "verify", "-CAfile", str(made.ca), str(h.cert)], capture_output=True, text=True)
        assert out.returncode == 0 and out.stdout.strip().endswith("OK"), out.stdout + out.stderr


def test_an_existing_authority_is_kept_unless_forced_and_can_sign_new_hosts(tmp_path):
    first = make_site_certs(tmp_path, site="flat", cameras=["cam1"])
    ca_before = first.ca.read_bytes()
    with pytest.raises(CertError, match="already exists.*--reuse-ca.*--force"):
        make_site_certs(tmp_path, site="flat", cameras=["cam1"])
    assert first.ca.read_bytes() == ca_before
    cam1_before = (tmp_path / "cam1.pem").read_bytes()
    again = make_site_certs(tmp_path, site="flat", cameras=["cam1", "cam2"], readers=["tablet"], reuse_ca=True)
    assert first.ca.read_bytes() == ca_before and again.ca_reused
    assert [h.host for h in again.hosts] == ["cam2", "tablet"]  # only the new hosts
    assert (tmp_path / "cam1.pem").read_bytes() == cam1_before
    ca = x509.load_pem_x509_certificate(ca_before)
    assert x509.load_pem_x509_certificate((tmp_path / "cam2.pem").read_bytes()).issuer == ca.subject
    forced = make_site_certs(tmp_path, site="flat", cameras=["cam1"], force=True)
    assert forced.ca.read_bytes() != ca_before


@pytest.mark.parametrize("kwargs, match", [
    (dict(cameras=["router"]), "taken"),
    (dict(cameras=["cam1"], readers=["cam1"]), "taken"),
    (dict(cameras=["a/b"]), "forbidden"),
    (dict(cameras=["cam1"], names={"cam9": ["x"]}), "cam9"),
    (dict(cameras=["cam1"], days=0), "days"),
    (dict(cameras=["cam1"], force=True, reuse_ca=True), "not both"),
    (dict(cameras=["cam1"], reuse_ca=True), "no authority"),
])
def test_refuses_what_cannot_be_made(tmp_path, kwargs, match):
    with pytest.raises(ValueError, match=match):
        make_site_certs(tmp_path / "c", site="flat", **kwargs)


def test_common_names():
    assert [common_name("router"), common_name("fusion"), common_name("camera", "cam1"), common_name("reader", "x")] == \
        ["router", "fusion", "camera-cam1", "reader-x"]
    with pytest.raises(ValueError):
        common_name("camera", "*")


def test_certs_command_writes_into_the_site_folder_names_the_endpoint_hosts_and_says_what_goes_where(tmp_path, capsys):
    site_file, _ = write_site(tmp_path)
    with site_file.open("a") as f:
        f.write('\n[zenoh]\nmode = "client"\nconnect = ["tls/fusion.local:7447"]\n')
    assert cli_main(["certs", "--site", str(site_file), "--reader", "tablet", "--name", "c1=cam1.local"]) == 0
    out = capsys.readouterr().out
    folder = site_file.parent / "certs"
    assert "new authority" in out and "camera host c1: ca.pem, c1.pem, c1-key.pem" in out
    assert "reader tablet" in out and "keep ca-key.pem off the network" in out
    assert "[zenoh.tls]" in out  # the site has no TLS section yet: what to add
    assert "fusion.local" in _sans(folder / "router.pem") and "fusion.local" in _sans(folder / "fusion.pem")
    assert "cam1.local" in _sans(folder / "c1.pem") and "cam1.local" not in _sans(folder / "c2.pem")
    assert (folder / "tablet.pem").is_file() and not (folder / "reader.pem").exists()
    assert cli_main(["certs", "--site", str(site_file)]) == 2  # the authority exists
    assert "already exists" in capsys.readouterr().err


def test_certs_command_says_when_a_reader_is_not_among_the_sites_readers(tmp_path, capsys):
    site_file, _ = write_site(tmp_path)
    with site_file.open("a") as f:
        f.write('\n[zenoh]\nmode = "client"\n[zenoh.tls]\nca = "keys/ca.pem"\ncerts = "keys"\nreaders = ["reader"]\n')
    assert cli_main(["certs", "--site", str(site_file), "--reader", "reader", "--reader", "phone"]) == 0
    out = capsys.readouterr().out
    assert (site_file.parent / "keys" / "phone.pem").is_file()  # the site's certs folder
    assert "add phone to [zenoh.tls] readers" in out and "then add to the site file" not in out
