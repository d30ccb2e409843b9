"""OPC UA security: what each address offers, users files, and a real encrypted session with
user name and password (Basic256Sha256 SignAndEncrypt) on loopback."""

from __future__ import annotations

import asyncio

import pytest

pytest.importorskip("asyncua")

from asyncua import Client, ua  # noqa: E402
from asyncua.crypto import cert_gen  # noqa: E402
from cryptography import x509  # noqa: E402
from cryptography.hazmat.primitives import serialization  # noqa: E402
from cryptography.x509.oid import ExtendedKeyUsageOID  # noqa: E402

from controller.opcua.server import (  # noqa: E402
    OpcUaSecurity,
    OpcUaServer,
    endpoint_security,
    hash_password,
    load_users,
)

NONE = ua.SecurityPolicyType.NoSecurity
ENCRYPTED = ua.SecurityPolicyType.Basic256Sha256_SignAndEncrypt


@pytest.mark.parametrize(("host", "cert", "users", "policies", "tokens"), [
    ("127.0.0.1", False, False, {NONE}, {ua.AnonymousIdentityToken}),
    ("::1", False, False, {NONE}, {ua.AnonymousIdentityToken}),
    ("localhost", True, True, {NONE, ENCRYPTED},
     {ua.AnonymousIdentityToken, ua.UserNameIdentityToken}),
    ("192.168.0.20", True, True, {ENCRYPTED}, {ua.UserNameIdentityToken}),
    ("0.0.0.0", True, True, {ENCRYPTED}, {ua.UserNameIdentityToken}),
])
def test_offered_security(host, cert, users, policies, tokens):
    p, t = endpoint_security(host, has_certificate=cert, has_users=users)
    assert set(p) == policies and set(t) == tokens
    if host not in ("127.0.0.1", "::1", "localhost"):
        assert NONE not in p and ua.AnonymousIdentityToken not in t


@pytest.mark.parametrize(("cert", "users"), [(False, False), (True, False), (False, True)])
def test_non_loopback_without_both_is_refused(cert, users):
    with pytest.raises(ValueError, match="non-loopback"):
        endpoint_security("10.0.0.5", has_certificate=cert, has_users=users)


def test_users_file_round_trip_and_errors(tmp_path):
    f = tmp_path / "users.txt"
    f.write_text("# plant users\nmes:" + hash_password("s3cret", salt=b"0" * 16, iterations=1000)
                 + "\n\n", encoding="utf-8")
    users = load_users(f)
    assert list(users) == ["mes"] and "s3cret" not in users["mes"]
    for bad in ("mes:s3cret\n", "", ":pbkdf2_sha256$1$00$00\n"):
        f.write_text(bad, encoding="utf-8")
        with pytest.raises(ValueError, match="users"):
            load_users(f)


def _cert(tmp_path):
    key = cert_gen.generate_private_key()
    cert = cert_gen.generate_self_signed_app_certificate(
        key, "smart-planer", {},
        [x509.UniformResourceIdentifier("urn:smart-planer:server"), x509.DNSName("localhost")],
        [ExtendedKeyUsageOID.SERVER_AUTH, ExtendedKeyUsageOID.CLIENT_AUTH],
        days=2)
    cert_path, key_path = tmp_path / "cert.der", tmp_path / "key.pem"
    cert_path.write_bytes(cert.public_bytes(serialization.Encoding.DER))
    key_path.write_bytes(cert_gen.dump_private_key_as_pem(key))
    return cert_path, key_path


def test_missing_security_files_are_named(tmp_path):
    with pytest.raises(ValueError, match="certificate: no such file"):
        OpcUaServer("opc.tcp://127.0.0.1:0", security=OpcUaSecurity(
            certificate=tmp_path / "nope.der", private_key=tmp_path / "nope.pem"))


def test_encrypted_session_with_password(tmp_path):
    cert_path, key_path = _cert(tmp_path)
    users = tmp_path / "users.txt"
    users.write_text("mes:" + hash_password("s3cret", iterations=1000) + "\n", encoding="utf-8")
    # the client's own application certificate
    ckey = cert_gen.generate_private_key()
    ccert = cert_gen.generate_self_signed_app_certificate(
        ckey, "client", {}, [x509.UniformResourceIdentifier("urn:test:client")],
        [ExtendedKeyUsageOID.CLIENT_AUTH], days=2)
    (tmp_path / "c.der").write_bytes(ccert.public_bytes(serialization.Encoding.DER))
    (tmp_path / "c.pem").write_bytes(cert_gen.dump_private_key_as_pem(ckey))
    security = f"Basic256Sha256,SignAndEncrypt,{tmp_path / 'c.der'},{tmp_path / 'c.pem'}"

    async def go():
        srv = OpcUaServer("opc.tcp://127.0.0.1:0", identification={"SerialNumber": "S1"},
                          security=OpcUaSecurity(certificate=cert_path, private_key=key_path,
                                                 users_file=users))
        await srv.start()
        try:
            async def session(password):
                c = Client(srv.endpoint)
                c.application_uri = "urn:test:client"
                await c.set_security_string(security)
                c.set_user("mes")
                c.set_password(password)
                async with c:
                    policy = c.security_policy
                    di = await c.get_namespace_index("http://opcfoundation.org/UA/DI/")
                    node = c.get_node(srv.nodes.machine.nodeid)
                    serial = await node.get_child([f"{di}:Identification", f"{di}:SerialNumber"])
                    value = await serial.read_value()
                    with pytest.raises(ua.UaStatusCodeError):
                        await serial.write_value(ua.DataValue(ua.Variant("x",
                                                                         ua.VariantType.String)))
                    return policy, value

            policy, value = await session("s3cret")
            assert value == "S1"
            assert policy.Mode == ua.MessageSecurityMode.SignAndEncrypt
            assert "Basic256Sha256" in policy.URI
            with pytest.raises(ua.UaStatusCodeError):
                await session("wrong")
        finally:
            await srv.stop()

    asyncio.run(go())
