"""A real mosquitto for the bridge's tests: started on a free loopback port with a
generated configuration (anonymous, a password file, or TLS with a generated
self-signed CA), stopped (or killed, and started again on the same port) by pid.

    with Broker(tmp_path) as broker:              # anonymous
        broker.url                                 # "mqtt://127.0.0.1:PORT"
    with Broker(tmp_path, users={"edge": "s3cret"}) as broker: ...
    with Broker(tmp_path, tls=True) as broker:     # broker.ca: the CA's PEM file
        broker.kill(); broker.start()              # SIGKILL, then back on the same port
"""

from __future__ import annotations

import datetime
import ipaddress
import os
import shutil
import signal
import socket
import subprocess
import time
from pathlib import Path
from types import TracebackType

import pytest

MOSQUITTO = shutil.which("mosquitto") or "/usr/sbin/mosquitto"
MOSQUITTO_PASSWD = shutil.which("mosquitto_passwd") or "/usr/bin/mosquitto_passwd"


def need_mosquitto() -> None:
    if not os.path.exists(MOSQUITTO):
        if os.environ.get("CI"):
            pytest.fail("mosquitto is not installed (make system-packages installs it)")
        pytest.skip("mosquitto is not installed (apt-get install mosquitto mosquitto-clients)")


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def make_ca(directory: Path, host: str = "localhost") -> tuple[Path, Path, Path]:
    """A self-signed CA and a server certificate it signs for ``host`` and 127.0.0.1:
    (ca.pem, server.pem, server.key)."""
    from cryptography import x509
    from cryptography.hazmat.primitives import hashes, serialization
    from cryptography.hazmat.primitives.asymmetric import ec
    from cryptography.x509.oid import NameOID

    now = datetime.datetime.now(datetime.timezone.utc)
    ca_key = ec.generate_private_key(ec.SECP256R1())
    ca_name = x509.Name([x509.NameAttribute(NameOID.COMMON_NAME, "pyrtu test CA")])
    ca = (
        x509.CertificateBuilder()
        .subject_name(ca_name)
        .issuer_name(ca_name)
        .public_key(ca_key.public_key())
        .serial_number(x509.random_serial_number())
        .not_valid_before(now - datetime.timedelta(minutes=5))
        .not_valid_after(now + datetime.timedelta(days=2))
        .add_extension(x509.BasicConstraints(ca=True, path_length=0), critical=True)
        .add_extension(
            x509.KeyUsage(False, False, False, False, False, True, True, False, False),
            critical=True,
        )
        .sign(ca_key, hashes.SHA256())
    )
    key = ec.generate_private_key(ec.SECP256R1())
    cert = (
        x509.CertificateBuilder()
        .subject_name(x509.Name([x509.NameAttribute(NameOID.COMMON_NAME, host)]))
        .issuer_name(ca_name)
        .public_key(key.public_key())
        .serial_number(x509.random_serial_number())
        .not_valid_before(now - datetime.timedelta(minutes=5))
        .not_valid_after(now + datetime.timedelta(days=2))
        .add_extension(
            x509.SubjectAlternativeName(
                [x509.DNSName(host), x509.IPAddress(ipaddress.ip_address("127.0.0.1"))]
            ),
            critical=False,
        )
        .sign(ca_key, hashes.SHA256())
    )
    pem = serialization.Encoding.PEM
    ca_path, cert_path, key_path = (
        directory / "ca.pem",
        directory / "server.pem",
        directory / "server.key",
    )
    ca_path.write_bytes(ca.public_bytes(pem))
    cert_path.write_bytes(cert.public_bytes(pem))
    key_path.write_bytes(
        key.private_bytes(pem, serialization.PrivateFormat.PKCS8, serialization.NoEncryption())
    )
    return ca_path, cert_path, key_path


class Broker:
    """One mosquitto process (see the module docstring)."""

    def __init__(
        self,
        directory: Path,
        *,
        users: dict[str, str] | None = None,
        tls: bool = False,
        port: int | None = None,
    ) -> None:
        need_mosquitto()
        self.dir = Path(directory) / f"broker-{id(self):x}"
        self.dir.mkdir(parents=True, exist_ok=True)
        self.port = port or free_port()
        self.tls = tls
        self.proc: subprocess.Popen[bytes] | None = None
        self.log = self.dir / "mosquitto.log"
        self.ca: Path | None = None
        lines = [
            f"listener {self.port} 127.0.0.1",
            "persistence false",
            "log_dest stderr",
            "log_type error",
            "log_type warning",
            "max_queued_messages 1000000",
            "max_inflight_messages 0",
            "set_tcp_nodelay true",
        ]
        if os.geteuid() == 0:  # else mosquitto drops to its own user and cannot read our files
            lines.append("user root")
        if users:
            pw = self.dir / "passwd"
            for i, (user, password) in enumerate(users.items()):
                cmd = [MOSQUITTO_PASSWD, "-b", *(["-c"] if i == 0 else []), str(pw), user, password]
                subprocess.run(cmd, check=True, capture_output=True)
            os.chmod(pw, 0o600)
            lines += ["allow_anonymous false", f"password_file {pw}"]
        else:
            lines.append("allow_anonymous true")
        if tls:
            self.ca, cert, key = make_ca(self.dir)
            lines += [f"cafile {self.ca}", f"certfile {cert}", f"keyfile {key}"]
        self.conf = self.dir / "mosquitto.conf"
        self.conf.write_text("\n".join(lines) + "\n")

    @property
    def url(self) -> str:
        host = "localhost" if self.tls else "127.0.0.1"  # the certificate's name
        return f"{'mqtts' if self.tls else 'mqtt'}://{host}:{self.port}"

    def start(self, patience: float = 10.0) -> Broker:
        assert self.proc is None or self.proc.poll() is not None, "already running"
        err = open(self.log, "ab")
        self.proc = subprocess.Popen([MOSQUITTO, "-c", str(self.conf)], stdout=err, stderr=err)
        err.close()
        give_up = time.monotonic() + patience
        while True:
            if self.proc.poll() is not None:
                raise RuntimeError(
                    f"mosquitto exited {self.proc.returncode}: {self.log.read_text()}"
                )
            try:
                with socket.create_connection(("127.0.0.1", self.port), timeout=0.2):
                    return self
            except OSError:
                if time.monotonic() > give_up:
                    self.stop()
                    raise RuntimeError(f"mosquitto did not listen on {self.port}") from None
                time.sleep(0.02)

    def kill(self) -> None:
        """SIGKILL (no clean shutdown), by pid."""
        if self.proc is not None and self.proc.poll() is None:
            os.kill(self.proc.pid, signal.SIGKILL)
            self.proc.wait(5)

    def stop(self) -> None:
        if self.proc is not None and self.proc.poll() is None:
            os.kill(self.proc.pid, signal.SIGTERM)
            try:
                self.proc.wait(5)
            except subprocess.TimeoutExpired:
                os.kill(self.proc.pid, signal.SIGKILL)
                self.proc.wait(5)

    def __enter__(self) -> Broker:
        return self.start()

    def __exit__(
        self, t: type[BaseException] | None, e: BaseException | None, tb: TracebackType | None
    ) -> None:
        self.stop()


class Client:
    """A paho MQTT 5 client on a thread of its own (loop_start) that records every
    message it receives: ``messages`` [(topic, payload, retain, properties, time)]."""

    def __init__(
        self,
        broker: Broker,
        topics: list[str] | None = None,
        *,
        client_id: str = "",
        username: str | None = None,
        password: str | None = None,
    ) -> None:
        import threading

        import paho.mqtt.client as mqtt
        from paho.mqtt.enums import CallbackAPIVersion

        self.messages: list[tuple[str, bytes, bool, object, float]] = []
        self._lock = threading.Lock()
        self._ready = threading.Event()
        c = mqtt.Client(CallbackAPIVersion.VERSION2, client_id=client_id, protocol=mqtt.MQTTv5)
        if username is not None:
            c.username_pw_set(username, password)
        if broker.tls:
            assert broker.ca is not None
            c.tls_set(ca_certs=str(broker.ca))
        subs = topics or []

        def on_connect(
            client: object, userdata: object, flags: object, rc: object, props: object
        ) -> None:
            if subs:
                c.subscribe([(t, 1) for t in subs])
            else:
                self._ready.set()

        def on_subscribe(*args: object) -> None:
            self._ready.set()

        def on_message(client: object, userdata: object, msg: mqtt.MQTTMessage) -> None:
            with self._lock:
                self.messages.append(
                    (msg.topic, bytes(msg.payload), bool(msg.retain), msg.properties, time.time())
                )

        c.on_connect = on_connect
        c.on_subscribe = on_subscribe
        c.on_message = on_message
        host = "localhost" if broker.tls else "127.0.0.1"
        c.connect(host, broker.port, 30)
        c.loop_start()
        self.client = c
        assert self._ready.wait(10), "the test client did not connect"

    def publish(
        self,
        topic: str,
        payload: bytes,
        *,
        qos: int = 1,
        retain: bool = False,
        properties: object = None,
    ) -> None:
        info = self.client.publish(topic, payload, qos, retain, properties)  # type: ignore[arg-type]
        info.wait_for_publish(10)

    def on(self, topic: str) -> list[bytes]:
        with self._lock:
            return [m[1] for m in self.messages if m[0] == topic]

    def wait(self, condition: object, what: str, patience: float = 30.0) -> None:
        give_up = time.monotonic() + patience
        while not condition():  # type: ignore[operator]
            assert time.monotonic() < give_up, f"gave up waiting for {what}"
            time.sleep(0.02)

    def close(self) -> None:
        self.client.disconnect()
        self.client.loop_stop()

    def __enter__(self) -> Client:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


__all__ = ["Broker", "Client", "Gate", "free_port", "make_ca", "need_mosquitto"]


class Gate:
    """A TCP relay (socat, by pid) in front of a broker's port: the bridge connects
    through it, so that a test decides when the bridge may reach the broker again."""

    def __init__(self, broker: Broker) -> None:
        self.broker = broker
        self.port = free_port()
        self.proc: subprocess.Popen[bytes] | None = None

    @property
    def url(self) -> str:
        return f"mqtt://127.0.0.1:{self.port}"

    def open(self, patience: float = 10.0) -> None:
        socat = shutil.which("socat")
        if socat is None:
            pytest.skip("socat is not installed")
        self.proc = subprocess.Popen(
            [
                socat,
                f"TCP-LISTEN:{self.port},bind=127.0.0.1,reuseaddr,fork",
                f"TCP:127.0.0.1:{self.broker.port}",
            ],
            stdout=subprocess.DEVNULL,
            stderr=subprocess.DEVNULL,
        )
        give_up = time.monotonic() + patience
        while True:
            try:
                with socket.create_connection(("127.0.0.1", self.port), timeout=0.2):
                    return
            except OSError:
                assert time.monotonic() < give_up, "socat did not listen"
                time.sleep(0.02)

    def close(self) -> None:
        """Stop relaying (the relays of open connections end with it)."""
        if self.proc is not None and self.proc.poll() is None:
            self.proc.kill()
            self.proc.wait(5)
        # the forked children of open connections: ended by the broker's close

    def __enter__(self) -> Gate:
        self.open()
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()
