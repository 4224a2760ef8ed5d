"""Mutual TLS and per-role access control with Zenoh's own mechanisms.

A secure deployment is a directory of PEM files made by ``lelsonar secure init``:

=========================  ===============================================
``ca.pem`` / ``ca.key``     the deployment's certificate authority (keep ``ca.key`` off the robots)
``router.pem`` / ``.key``   the router; its SANs name the hosts clients dial
``acquire-<id>.pem/.key``   one per scanner; CN ``acquire-<id>``
``reconstruct.pem/.key``    the reconstruction service
``planner.pem/.key``        any consumer of plane estimates
=========================  ===============================================

Every process is a Zenoh *client* of one router over ``tls/`` with mutual TLS.
The router carries the access-control rules: deny by default, then what each
role may do, keyed by the certificate's common name (:func:`access_control`).
A sender needs an *ingress* rule for a message and the receiver the matching
*egress* rule; a declared publisher also needs an egress ``declare_subscriber``
rule, or it never learns that anyone listens.

Private keys are written 0600 and replaced only by :func:`rotate` (``lelsonar secure rotate``).
"""

from __future__ import annotations

import dataclasses
import datetime as dt
import ipaddress
import json
import os
from collections.abc import Iterable
from dataclasses import dataclass
from pathlib import Path

from cryptography import x509
from cryptography.exceptions import InvalidSignature
from cryptography.hazmat.primitives import hashes, serialization
from cryptography.hazmat.primitives.asymmetric import ec
from cryptography.x509.oid import ExtendedKeyUsageOID, NameOID

from lelsonar.errors import SecurityError
from lelsonar.keys import DEFAULT_PREFIX, validate_identifier, validate_prefix
from lelsonar.net.transport import DEFAULT_ENDPOINT, ZenohSettings

ROUTER, RECONSTRUCT, PLANNER, MAPPER = "router", "reconstruct", "planner", "mapper"
ACQUIRE_PREFIX = "acquire-"
DEFAULT_HOSTS = ("localhost", "127.0.0.1")
DEFAULT_DAYS = 365
CA_DAYS = 3650
#: Endpoint schemes a secure session can use: TCP endpoints are switched to TLS.
_PLAIN_TO_TLS = {"tcp/": "tls/", "tls/": "tls/"}


def acquire_role(scanner_id: str) -> str:
    """The role (and certificate common name) of the acquisition service of one scanner."""
    return ACQUIRE_PREFIX + validate_identifier(scanner_id)


def validate_role(role: str) -> str:
    if role in (ROUTER, RECONSTRUCT, PLANNER, MAPPER):
        return role
    if role.startswith(ACQUIRE_PREFIX):
        acquire_role(role[len(ACQUIRE_PREFIX) :])
        return role
    raise SecurityError(
        f"unknown role {role!r}; roles are router, reconstruct, planner, mapper and acquire-<scanner id>"
    )


# --- the directory of certificates ----------------------------------------------------
@dataclass(frozen=True)
class SecureDir:
    """Where the CA and the role certificates of one deployment live."""

    path: Path

    @property
    def ca_cert(self) -> Path:
        return self.path / "ca.pem"

    @property
    def ca_key(self) -> Path:
        return self.path / "ca.key"

    def cert(self, role: str) -> Path:
        return self.path / f"{validate_role(role)}.pem"

    def key(self, role: str) -> Path:
        return self.path / f"{validate_role(role)}.key"

    def scanners(self) -> tuple[str, ...]:
        """Scanner ids that have an acquire certificate here, sorted."""
        if not self.path.is_dir():
            return ()
        return tuple(sorted(p.stem[len(ACQUIRE_PREFIX) :] for p in self.path.glob(f"{ACQUIRE_PREFIX}*.pem")))

    def require(self, role: str) -> None:
        """Raise :class:`SecurityError` unless the CA and the role's certificate and key are usable."""

        missing = [p for p in (self.ca_cert, self.cert(role), self.key(role)) if not p.is_file()]
        if missing:
            fix = (
                f"lelsonar secure add-scanner {self.path} {role[len(ACQUIRE_PREFIX) :]}"
                if role.startswith(ACQUIRE_PREFIX)
                else f"lelsonar secure init {self.path} --scanner ID"
            )
            raise SecurityError(
                f"missing {', '.join(str(p) for p in missing)} for role {role!r}; create it with "
                f"`{fix}` (or copy it there from the machine that holds the CA)"
            )
        ca = x509.load_pem_x509_certificate(self.ca_cert.read_bytes())
        cert = x509.load_pem_x509_certificate(self.cert(role).read_bytes())
        try:
            cert.verify_directly_issued_by(ca)
        except (ValueError, TypeError, InvalidSignature) as exc:
            raise SecurityError(
                f"{self.cert(role)} was not issued by {self.ca_cert} ({exc.__class__.__name__}); "
                f"re-issue it with the CA of this directory"
            ) from None
        now = dt.datetime.now(dt.UTC)
        if not cert.not_valid_before_utc <= now <= cert.not_valid_after_utc:
            raise SecurityError(
                f"{self.cert(role)} is valid only from {cert.not_valid_before_utc:%Y-%m-%d} to "
                f"{cert.not_valid_after_utc:%Y-%m-%d}; rotate it with `lelsonar secure rotate "
                f"{self.path} {role}`"
            )
        if common_name(cert) != role:
            raise SecurityError(
                f"{self.cert(role)} has common name {common_name(cert)!r}, not {role!r}; "
                "the access rules are keyed by it, so re-issue the certificate"
            )


def common_name(cert) -> str:

    names = cert.subject.get_attributes_for_oid(NameOID.COMMON_NAME)
    return str(names[0].value) if names else ""


def _new_key():

    return ec.generate_private_key(ec.SECP256R1())


def _key_pem(key) -> bytes:

    return key.private_bytes(
        serialization.Encoding.PEM, serialization.PrivateFormat.PKCS8, serialization.NoEncryption()
    )


def _write(path: Path, data: bytes, *, private: bool, replace: bool = False) -> None:
    """Write a new file; a private one is 0600 from its creation.  Never replaces unless ``replace``."""
    target = path.with_name(path.name + ".new") if replace else path
    try:
        fd = os.open(target, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o600 if private else 0o644)
    except FileExistsError:
        raise SecurityError(
            f"{target} already exists; lelsonar never overwrites keys or certificates silently "
            "(replace a role's with `lelsonar secure rotate DIR ROLE`; remove a stale .new "
            "file)"
        ) from None
    with os.fdopen(fd, "wb") as f:
        if private:
            os.fchmod(f.fileno(), 0o600)  # whatever the umask said
        f.write(data)
    if replace:
        os.replace(target, path)


def _load_ca(d: SecureDir):

    if not (d.ca_cert.is_file() and d.ca_key.is_file()):
        raise SecurityError(
            f"{d.path} holds no CA (ca.pem and ca.key); create one with `lelsonar secure init {d.path} --scanner ID`"
        )
    return (
        x509.load_pem_x509_certificate(d.ca_cert.read_bytes()),
        serialization.load_pem_private_key(d.ca_key.read_bytes(), password=None),
    )


def _issue(
    d: SecureDir, role: str, *, hosts: Iterable[str] = (), days: int = DEFAULT_DAYS, replace: bool = False
) -> list[Path]:

    ca_cert, ca_key = _load_ca(d)
    key = _new_key()
    now = dt.datetime.now(dt.UTC)
    builder = (
        x509.CertificateBuilder()
        .subject_name(x509.Name([x509.NameAttribute(NameOID.COMMON_NAME, role)]))
        .issuer_name(ca_cert.subject)
        .public_key(key.public_key())
        .serial_number(x509.random_serial_number())
        .not_valid_before(now - dt.timedelta(minutes=5))
        .not_valid_after(now + dt.timedelta(days=days))
        .add_extension(x509.BasicConstraints(ca=False, path_length=None), critical=True)
        .add_extension(
            x509.KeyUsage(
                digital_signature=True,
                key_encipherment=False,
                content_commitment=False,
                data_encipherment=False,
                key_agreement=True,
                key_cert_sign=False,
                crl_sign=False,
                encipher_only=False,
                decipher_only=False,
            ),
            critical=True,
        )
        .add_extension(
            x509.ExtendedKeyUsage([ExtendedKeyUsageOID.SERVER_AUTH, ExtendedKeyUsageOID.CLIENT_AUTH]), critical=False
        )
    )
    names: list[x509.GeneralName] = []
    for host in hosts:
        try:
            names.append(x509.IPAddress(ipaddress.ip_address(host)))
        except ValueError:
            names.append(x509.DNSName(host))
    if names:
        builder = builder.add_extension(x509.SubjectAlternativeName(names), critical=False)
    cert = builder.sign(ca_key, hashes.SHA256())

    if not replace and (d.key(role).exists() or d.cert(role).exists()):
        raise SecurityError(
            f"{d.cert(role)} or its key already exists; lelsonar never overwrites them silently "
            f"(to replace them: `lelsonar secure rotate {d.path} {role}`)"
        )
    _write(d.key(role), _key_pem(key), private=True, replace=replace)
    _write(d.cert(role), cert.public_bytes(serialization.Encoding.PEM), private=False, replace=replace)
    return [d.cert(role), d.key(role)]


def init(
    path: Path | str, scanners: Iterable[str], *, hosts: Iterable[str] = (), days: int = DEFAULT_DAYS
) -> list[Path]:
    """Create a CA and the certificates of the router, reconstruct, planner, mapper and one acquire per scanner.

    The router's certificate names ``localhost``, ``127.0.0.1`` and ``hosts`` (what remote clients dial).

    Raises
    ------
    SecurityError
        If the directory already holds a CA (nothing is overwritten), or cannot be made.
    """

    d = SecureDir(Path(path))
    scanners = [validate_identifier(s) for s in scanners]
    if not scanners:
        raise SecurityError("name at least one scanner: `lelsonar secure init DIR --scanner scanner1`")
    if d.ca_key.exists() or d.ca_cert.exists():
        raise SecurityError(
            f"{d.path} already holds a CA; add scanners with `lelsonar secure add-scanner "
            f"{d.path} ID`, or init into a new directory to start over (nothing was overwritten)"
        )
    roles = (ROUTER, RECONSTRUCT, PLANNER, MAPPER, *(acquire_role(s) for s in scanners))
    if taken := [str(p) for r in roles for p in (d.cert(r), d.key(r)) if p.exists()]:
        raise SecurityError(
            f"{', '.join(taken)} already exist without a CA here; init into a new directory (nothing was overwritten)"
        )
    try:
        d.path.mkdir(parents=True, exist_ok=True, mode=0o700)
    except OSError as exc:  # a file in the way, a folder that cannot be made
        raise SecurityError(f"cannot make the directory {d.path}: {exc.strerror}; give a new directory") from None
    key = _new_key()
    now = dt.datetime.now(dt.UTC)
    name = x509.Name([x509.NameAttribute(NameOID.COMMON_NAME, "lelsonar CA")])
    ca = (
        x509.CertificateBuilder()
        .subject_name(name)
        .issuer_name(name)
        .public_key(key.public_key())
        .serial_number(x509.random_serial_number())
        .not_valid_before(now - dt.timedelta(minutes=5))
        .not_valid_after(now + dt.timedelta(days=CA_DAYS))
        .add_extension(x509.BasicConstraints(ca=True, path_length=0), critical=True)
        .add_extension(
            x509.KeyUsage(
                digital_signature=True,
                key_encipherment=False,
                content_commitment=False,
                data_encipherment=False,
                key_agreement=False,
                key_cert_sign=True,
                crl_sign=True,
                encipher_only=False,
                decipher_only=False,
            ),
            critical=True,
        )
        .add_extension(x509.SubjectKeyIdentifier.from_public_key(key.public_key()), critical=False)
        .sign(key, hashes.SHA256())
    )
    _write(d.ca_key, _key_pem(key), private=True)
    _write(d.ca_cert, ca.public_bytes(serialization.Encoding.PEM), private=False)
    created = [d.ca_cert, d.ca_key]
    # Services on the router's own host dial it by loopback; --host adds the names others dial.
    created += _issue(d, ROUTER, hosts=dict.fromkeys((*DEFAULT_HOSTS, *hosts)), days=days)
    for role in roles[1:]:
        created += _issue(d, role, days=days)
    return created


def add_scanner(path: Path | str, scanner_id: str, *, days: int = DEFAULT_DAYS) -> list[Path]:
    """Issue ``acquire-<id>``'s certificate (the router's rules include it once restarted)."""
    d = SecureDir(Path(path))
    role = acquire_role(scanner_id)
    if d.cert(role).exists() or d.key(role).exists():
        raise SecurityError(
            f"{d.cert(role)} already exists; to replace its key and certificate run "
            f"`lelsonar secure rotate {d.path} {role}`"
        )
    return _issue(d, role, days=days)


def rotate(path: Path | str, role: str, *, hosts: Iterable[str] | None = None, days: int = DEFAULT_DAYS) -> list[Path]:
    """Replace a role's key and certificate with new ones from the same CA; the common name stays.

    The router's new certificate names the same hosts as the old one unless ``hosts`` is given
    (loopback is always named).
    """

    d = SecureDir(Path(path))
    validate_role(role)
    if not d.cert(role).exists():
        raise SecurityError(
            f"{d.cert(role)} does not exist, so there is nothing to rotate; issue it with "
            + (
                f"`lelsonar secure add-scanner {d.path} {role[len(ACQUIRE_PREFIX) :]}`"
                if role.startswith(ACQUIRE_PREFIX)
                else "`lelsonar secure init` into a new directory"
            )
        )
    if role == ROUTER:
        if hosts is None:
            old = x509.load_pem_x509_certificate(d.cert(role).read_bytes())
            try:
                san = old.extensions.get_extension_for_class(x509.SubjectAlternativeName).value
                hosts = [
                    *san.get_values_for_type(x509.DNSName),
                    *(str(ip) for ip in san.get_values_for_type(x509.IPAddress)),
                ]
            except x509.ExtensionNotFound:
                hosts = []
        hosts = dict.fromkeys((*DEFAULT_HOSTS, *hosts))
    return _issue(d, role, hosts=hosts or (), days=days, replace=True)


# --- access control ----------------------------------------------------------------------
def _rule(rid: str, flow: str, messages: list[str], keys: list[str]) -> dict:
    return {"id": rid, "permission": "allow", "flows": [flow], "messages": messages, "key_exprs": keys}


def role_rules(role: str, prefix: str = DEFAULT_PREFIX) -> list[dict]:
    """What one role may do, as Zenoh ACL rules (ingress = it sends, egress = it receives)."""
    p = validate_prefix(prefix)
    validate_role(role)
    if role.startswith(ACQUIRE_PREFIX):
        sid = role[len(ACQUIRE_PREFIX) :]
        own = f"{p}/{sid}"
        return [
            _rule(f"{role}-put", "ingress", ["put"], [f"{own}/sample", f"{own}/scan"]),
            _rule(f"{role}-token", "ingress", ["liveliness_token"], [f"{own}/alive/**"]),
            _rule(f"{role}-serve-log", "ingress", ["declare_queryable", "reply"], [f"{own}/log/**"]),
            # Queries for every scanner's log reach it too; it can only answer for its own.
            _rule(f"{role}-log-queries", "egress", ["query"], [f"{p}/*/log/**", f"{own}/log/**"]),
            # A declared publisher sends only once it learns of matching subscribers.
            # The reconstructor's live source declares one subscriber on both keys: <prefix>/*/s$*.
            _rule(
                f"{role}-learn-subscribers",
                "egress",
                ["declare_subscriber"],
                [f"{p}/*/sample", f"{p}/*/scan", f"{p}/*/s$*", f"{own}/sample", f"{own}/scan"],
            ),
        ]
    if role == RECONSTRUCT:
        return [
            # One subscriber on both keys (sources.live_key: one channel keeps their order); the
            # egress rule below still lets only samples and scan events reach it.
            _rule(
                "reconstruct-subscribe",
                "ingress",
                ["declare_subscriber"],
                [f"{p}/*/sample", f"{p}/*/scan", f"{p}/*/s$*"],
            ),
            _rule("reconstruct-receive", "egress", ["put"], [f"{p}/*/sample", f"{p}/*/scan"]),
            _rule("reconstruct-publish", "ingress", ["put", "declare_queryable", "reply"], [f"{p}/*/planes"]),
            _rule("reconstruct-planes-queries", "egress", ["query"], [f"{p}/*/planes"]),
            _rule("reconstruct-learn-subscribers", "egress", ["declare_subscriber"], [f"{p}/*/planes"]),
            _rule("reconstruct-query-logs", "ingress", ["query"], [f"{p}/*/log/**"]),
            # Like publishers and subscribers: a querier's matching status needs the queryables' declarations.
            _rule("reconstruct-log-replies", "egress", ["reply", "declare_queryable"], [f"{p}/*/log/**"]),
            _rule("reconstruct-token", "ingress", ["liveliness_token"], [f"{p}/*/alive/reconstruct"]),
            _rule(
                "reconstruct-watch",
                "ingress",
                ["declare_liveliness_subscriber", "liveliness_query"],
                [f"{p}/*/alive/**"],
            ),
            _rule("reconstruct-see-tokens", "egress", ["liveliness_token"], [f"{p}/*/alive/**"]),
            # reconstruct --group: members' tokens, and the marks of the finals each member published.
            _rule(
                "reconstruct-group-token",
                "ingress",
                ["liveliness_token", "declare_liveliness_subscriber", "liveliness_query"],
                [f"{p}/_group/*/member/**"],
            ),
            _rule("reconstruct-group-see-tokens", "egress", ["liveliness_token"], [f"{p}/_group/*/member/**"]),
            _rule("reconstruct-group-done", "ingress", ["put", "declare_subscriber"], [f"{p}/_group/*/done"]),
            _rule("reconstruct-group-done-receive", "egress", ["put", "declare_subscriber"], [f"{p}/_group/*/done"]),
            # The fence after a partition: each member's table of the finals it published.
            _rule(
                "reconstruct-group-finals",
                "ingress",
                ["declare_queryable", "reply", "query"],
                [f"{p}/_group/*/finals/*"],
            ),
            _rule(
                "reconstruct-group-finals-receive",
                "egress",
                ["declare_queryable", "reply", "query"],
                [f"{p}/_group/*/finals/*"],
            ),
        ]
    if role == PLANNER:
        return [
            _rule("planner-subscribe", "ingress", ["declare_subscriber", "query"], [f"{p}/*/planes"]),
            _rule("planner-receive", "egress", ["put", "reply", "declare_queryable"], [f"{p}/*/planes"]),
            _rule("planner-token", "ingress", ["liveliness_token"], [f"{p}/*/alive/planner"]),
            _rule(
                "planner-watch", "ingress", ["declare_liveliness_subscriber", "liveliness_query"], [f"{p}/*/alive/**"]
            ),
            _rule("planner-see-tokens", "egress", ["liveliness_token"], [f"{p}/*/alive/**"]),
            _rule("planner-map", "ingress", ["declare_subscriber", "query"], [f"{p}/map"]),
            _rule("planner-map-receive", "egress", ["put", "reply", "declare_queryable"], [f"{p}/map"]),
        ]
    if role == MAPPER:
        return [
            # The scans' poses and the estimates, as a planner reads the estimates.
            _rule("mapper-subscribe", "ingress", ["declare_subscriber", "query"], [f"{p}/*/scan", f"{p}/*/planes"]),
            _rule("mapper-receive", "egress", ["put", "reply", "declare_queryable"], [f"{p}/*/scan", f"{p}/*/planes"]),
            _rule("mapper-publish", "ingress", ["put", "declare_queryable", "reply"], [f"{p}/map"]),
            _rule("mapper-map-queries", "egress", ["query", "declare_subscriber"], [f"{p}/map"]),
        ]
    return []  # the router itself sends nothing of its own


def access_control(scanners: Iterable[str], prefix: str = DEFAULT_PREFIX) -> dict:
    """The router's ``access_control`` section: deny by default, one subject and policy per role."""
    roles = [RECONSTRUCT, PLANNER, MAPPER, *(acquire_role(s) for s in sorted(set(scanners)))]
    rules, subjects, policies = [], [], []
    for role in roles:
        mine = role_rules(role, prefix)
        rules += mine
        subjects.append({"id": role, "cert_common_names": [role]})
        policies.append({"id": role, "subjects": [role], "rules": [r["id"] for r in mine]})
    return {"enabled": True, "default_permission": "deny", "rules": rules, "subjects": subjects, "policies": policies}


# --- Zenoh configuration ----------------------------------------------------------------
def tls_endpoint(endpoint: str) -> str:
    """``tcp/H:P`` → ``tls/H:P``; ``tls/`` stays; anything else cannot carry mutual TLS."""
    for plain, tls in _PLAIN_TO_TLS.items():
        if endpoint.startswith(plain):
            return tls + endpoint[len(plain) :]
    raise SecurityError(
        f"endpoint {endpoint!r} cannot carry mutual TLS; use tls/HOST:PORT (or tcp/HOST:PORT, "
        "which --secure switches to tls/)"
    )


def overlay(directory: Path | str, role: str, prefix: str = DEFAULT_PREFIX) -> tuple[tuple[str, str], ...]:
    """The (JSON5 path, JSON value) pairs that make a session speak mutual TLS as ``role``.

    The router's overlay also carries the access-control rules for every scanner
    certificate in ``directory``.
    """
    d = SecureDir(Path(directory).resolve())
    d.require(role)
    tls = {"root_ca_certificate": str(d.ca_cert), "enable_mtls": True, "close_link_on_expiration": True}
    if role == ROUTER:
        tls |= {"listen_certificate": str(d.cert(role)), "listen_private_key": str(d.key(role))}
    else:
        tls |= {"connect_certificate": str(d.cert(role)), "connect_private_key": str(d.key(role))}
    pairs = [("transport/link/protocols", ["tls"]), ("transport/link/tls", tls)]
    if role == ROUTER:
        scanners = d.scanners()
        if not scanners:
            raise SecurityError(
                f"{d.path} has no acquire-<id> certificate, so no scanner could publish; add one "
                f"with `lelsonar secure add-scanner {d.path} ID`"
            )
        pairs.append(("access_control", access_control(scanners, prefix)))
    return tuple((path, json.dumps(value)) for path, value in pairs)


def secure_settings(
    settings: ZenohSettings, directory: Path | str, role: str, prefix: str | None = None
) -> ZenohSettings:
    """``settings`` switched to mutual TLS as ``role``.

    Every role but the router becomes a *client*: the router enforces the access
    rules, and a peer would accept connections that bypass them.
    """

    mode = "router" if role == ROUTER else "client"
    # A field left None takes the embedded default (no config file) or the file's value (see transport).
    no_file = settings.config_file is None
    connect = tuple(
        tls_endpoint(e)
        for e in (settings.connect if settings.connect is not None else ((DEFAULT_ENDPOINT,) if no_file else ()))
    )
    listen = tuple(tls_endpoint(e) for e in (settings.listen or ()))
    if mode == "client":
        if not connect:
            raise SecurityError("a secure client needs the router's endpoint: --connect tls/HOST:7447")
        if listen:
            raise SecurityError(
                "with --secure every process but the router is a client and listens on nothing; "
                "drop --listen (a listening peer would accept links that bypass the access rules)"
            )
    return dataclasses.replace(
        settings,
        mode=mode,
        connect=connect if mode == "client" else (),
        listen=listen,
        overlay=overlay(directory, role, prefix or DEFAULT_PREFIX),
    )


def role_config(
    directory: Path | str,
    role: str,
    *,
    prefix: str = DEFAULT_PREFIX,
    connect: Iterable[str] = (),
    listen: Iterable[str] = (),
) -> dict:
    """The whole Zenoh configuration of one role, for any Zenoh client or tool."""
    validate_role(role)
    config: dict = {"mode": "router" if role == ROUTER else "client", "scouting": {"multicast": {"enabled": False}}}
    if role == ROUTER:
        config["listen"] = {"endpoints": [tls_endpoint(e) for e in (listen or ("tls/127.0.0.1:7447",))]}
    else:
        config["connect"] = {"endpoints": [tls_endpoint(e) for e in (connect or ("tls/127.0.0.1:7447",))]}
    for path, value in overlay(directory, role, prefix):
        node = config
        *parents, leaf = path.split("/")
        for part in parents:
            node = node.setdefault(part, {})
        node[leaf] = json.loads(value)
    return config
