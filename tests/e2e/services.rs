//! The real services the multi-machine tests run beside dsrl-server, each on a free loopback port and stopped when
//! dropped: moto as S3 (from the pinned Python environment) and PostgreSQL from Debian's packages, initialised in a
//! temporary folder.

use std::io::{Read, Write};
use std::path::{Path, PathBuf};
use std::process::{Child, Command, Stdio};
use std::time::Duration;

use dsrl_e2e::{python, wait_for};

pub fn free_port() -> u16 {
    std::net::TcpListener::bind("127.0.0.1:0")
        .unwrap()
        .local_addr()
        .unwrap()
        .port()
}

/// An S3-protocol server (moto) with one bucket.
pub struct Moto {
    child: Child,
    pub endpoint: String,
    pub bucket: String,
}

impl Moto {
    pub fn start(bucket: &str) -> Moto {
        let port = free_port();
        let child = Command::new(python().with_file_name("moto_server"))
            .args(["-H", "127.0.0.1", "-p", &port.to_string()])
            .stdout(Stdio::null())
            .stderr(Stdio::null())
            .spawn()
            .expect("moto_server from the test environment");
        let moto = Moto {
            child,
            endpoint: format!("http://127.0.0.1:{port}"),
            bucket: bucket.to_owned(),
        };
        let up = wait_for(Duration::from_secs(30), || {
            std::net::TcpStream::connect(("127.0.0.1", port)).is_ok()
        });
        assert!(up, "moto did not start");
        // One plain HTTP request (the tests' async client needs a runtime; this is called from inside one).
        let mut stream = std::net::TcpStream::connect(("127.0.0.1", port)).unwrap();
        write!(
            stream,
            "PUT /{bucket} HTTP/1.1\r\nHost: 127.0.0.1:{port}\r\nContent-Length: 0\r\nConnection: close\r\n\r\n"
        )
        .unwrap();
        let mut answer = String::new();
        stream.read_to_string(&mut answer).unwrap();
        assert!(answer.starts_with("HTTP/1.1 200"), "creating the bucket: {answer}");
        moto
    }

    /// The server's settings for this bucket (credentials are moto's dummies).
    pub fn server_env(&self, prefix: &str) -> Vec<(String, String)> {
        [
            ("DSRL__STORAGE__BACKEND", "s3"),
            ("DSRL__STORAGE__S3__BUCKET", self.bucket.as_str()),
            ("DSRL__STORAGE__S3__PREFIX", prefix),
            ("DSRL__STORAGE__S3__ENDPOINT", self.endpoint.as_str()),
            ("DSRL__STORAGE__S3__ALLOW_HTTP", "true"),
            ("DSRL__STORAGE__S3__REGION", "us-east-1"),
            ("AWS_ACCESS_KEY_ID", "test"),
            ("AWS_SECRET_ACCESS_KEY", "test"),
        ]
        .into_iter()
        .map(|(k, v)| (k.to_owned(), v.to_owned()))
        .collect()
    }
}

impl Drop for Moto {
    fn drop(&mut self) {
        let _ = self.child.kill();
        let _ = self.child.wait();
    }
}

/// A PostgreSQL server (Debian's `postgresql` package, installed by `scripts/install-system-deps.sh --tests`) in
/// a temporary folder, trusting local connections, without fsync (a test database need not survive a crash of
/// the machine). PostgreSQL refuses to run as root, so under root it runs as the `postgres` user the package made.
pub struct Postgres {
    child: Child,
    _dir: tempfile::TempDir,
    pub url: String,
}

impl Postgres {
    pub fn start() -> Postgres {
        Postgres::start_with(false).0
    }

    /// A server that takes TLS connections only (plaintext ones from 127.0.0.1 are rejected by pg_hba.conf), with a
    /// certificate for 127.0.0.1 and localhost signed by a CA made for it; returns the CA's certificate file.
    pub fn start_tls() -> (Postgres, PathBuf) {
        let (postgres, ca) = Postgres::start_with(true);
        (postgres, ca.expect("a TLS server has a CA"))
    }

    fn start_with(tls: bool) -> (Postgres, Option<PathBuf>) {
        let bin = postgres_bin_dir();
        let dir = tempfile::tempdir().unwrap();
        let data = dir.path().join("data");
        let as_root = nix_is_root();
        if as_root {
            let status = Command::new("chown")
                .args(["postgres:postgres"])
                .arg(dir.path())
                .status()
                .unwrap();
            assert!(status.success(), "chown of the PostgreSQL folder");
        }
        let command = |program: &str| {
            let mut cmd = if as_root {
                let mut cmd = Command::new("setpriv");
                cmd.args(["--reuid=postgres", "--regid=postgres", "--init-groups"])
                    .arg(bin.join(program));
                cmd
            } else {
                Command::new(bin.join(program))
            };
            cmd.current_dir(dir.path());
            cmd
        };
        let init = command("initdb")
            .args(["-U", "dsrl", "-A", "trust", "-E", "UTF8", "--no-sync", "-D"])
            .arg(&data)
            .output()
            .expect("running initdb");
        assert!(
            init.status.success(),
            "initdb failed: {}",
            String::from_utf8_lossy(&init.stderr)
        );
        let ca = tls.then(|| {
            let ca = make_certificates(dir.path(), &data);
            if as_root {
                let status = Command::new("chown")
                    .args(["postgres:postgres"])
                    .arg(data.join("server.crt"))
                    .arg(data.join("server.key"))
                    .status()
                    .unwrap();
                assert!(status.success(), "chown of the server's key");
            }
            std::fs::write(
                data.join("pg_hba.conf"),
                "local all all trust\nhostssl all all 127.0.0.1/32 trust\nhostnossl all all 127.0.0.1/32 reject\n",
            )
            .unwrap();
            ca
        });
        let port = free_port();
        let log = std::fs::File::create(dir.path().join("postgres.log")).unwrap();
        let mut postgres = command("postgres");
        postgres
            .arg("-D")
            .arg(&data)
            .args(["-p", &port.to_string(), "-k"])
            .arg(dir.path())
            .args([
                "-c",
                "listen_addresses=127.0.0.1",
                "-c",
                "fsync=off",
                "-c",
                "max_connections=200",
            ]);
        if tls {
            postgres.args([
                "-c",
                "ssl=on",
                "-c",
                "ssl_cert_file=server.crt",
                "-c",
                "ssl_key_file=server.key",
            ]);
        }
        let child = postgres
            .stdout(Stdio::null())
            .stderr(log)
            .spawn()
            .expect("starting postgres");
        let postgres = Postgres {
            child,
            url: format!("postgres://dsrl@127.0.0.1:{port}/postgres"),
            _dir: dir,
        };
        let ready = wait_for(Duration::from_secs(60), || {
            Command::new(bin.join("pg_isready"))
                .args(["-q", "-h", "127.0.0.1", "-p", &port.to_string()])
                .status()
                .is_ok_and(|s| s.success())
        });
        assert!(ready, "PostgreSQL did not accept connections");
        (postgres, ca)
    }
}

/// A CA and a server certificate it signs (for 127.0.0.1 and localhost) in `data` as server.crt / server.key
/// (the key readable by its owner only, as PostgreSQL demands); returns the CA's certificate file, in `dir`.
fn make_certificates(dir: &Path, data: &Path) -> PathBuf {
    let openssl = |args: &[&str]| {
        let out = Command::new("openssl")
            .args(args)
            .current_dir(dir)
            .output()
            .expect("openssl is installed by scripts/install-system-deps.sh --tests");
        assert!(
            out.status.success(),
            "openssl {args:?}: {}",
            String::from_utf8_lossy(&out.stderr)
        );
    };
    let (key, crt) = (data.join("server.key"), data.join("server.crt"));
    let (key, crt) = (key.to_str().unwrap(), crt.to_str().unwrap());
    openssl(&[
        "req",
        "-x509",
        "-newkey",
        "rsa:2048",
        "-nodes",
        "-keyout",
        "ca.key",
        "-out",
        "ca.crt",
        "-days",
        "2",
        "-subj",
        "/CN=dsrl test CA",
    ]);
    openssl(&[
        "req",
        "-newkey",
        "rsa:2048",
        "-nodes",
        "-keyout",
        key,
        "-out",
        "server.csr",
        "-subj",
        "/CN=localhost",
    ]);
    std::fs::write(dir.join("san.ext"), "subjectAltName=IP:127.0.0.1,DNS:localhost\n").unwrap();
    openssl(&[
        "x509",
        "-req",
        "-in",
        "server.csr",
        "-CA",
        "ca.crt",
        "-CAkey",
        "ca.key",
        "-CAcreateserial",
        "-out",
        crt,
        "-days",
        "2",
        "-extfile",
        "san.ext",
    ]);
    std::fs::set_permissions(
        data.join("server.key"),
        std::os::unix::fs::PermissionsExt::from_mode(0o600),
    )
    .unwrap();
    dir.join("ca.crt")
}

impl Drop for Postgres {
    fn drop(&mut self) {
        let _ = self.child.kill();
        let _ = self.child.wait();
    }
}

/// The newest `/usr/lib/postgresql/<major>/bin` (Debian keeps the server binaries off PATH).
fn postgres_bin_dir() -> PathBuf {
    let root = Path::new("/usr/lib/postgresql");
    let mut majors: Vec<u32> = std::fs::read_dir(root)
        .unwrap_or_else(|e| panic!("{}: {e}; run scripts/install-system-deps.sh --tests", root.display()))
        .flatten()
        .filter_map(|e| e.file_name().to_str()?.parse().ok())
        .collect();
    majors.sort();
    let major = majors
        .last()
        .expect("a PostgreSQL major version under /usr/lib/postgresql");
    root.join(major.to_string()).join("bin")
}

fn nix_is_root() -> bool {
    Command::new("id")
        .arg("-u")
        .output()
        .is_ok_and(|o| String::from_utf8_lossy(&o.stdout).trim() == "0")
}
