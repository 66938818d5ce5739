//! A throw-away PostgreSQL cluster for tests: Debian's `initdb` + `pg_ctl` in a temporary directory,
//! listening on 127.0.0.1 only on a free port (and on a socket inside the directory), with a
//! password-protected superuser. One cluster per test binary, started on first use; a watchdog shell
//! stops it (`pg_ctl stop -m immediate`) and deletes the directory when the test process exits.
//!
//! initdb refuses to run as root: as root the cluster belongs to the `postgres` user that Debian's
//! package creates (commands run through `runuser`); as anyone else it belongs to that user.
//!
//! Without PostgreSQL the tests skip with a message, and fail under `CUBECAL_REQUIRE_TOOLS=1` (CI,
//! which installs it: deploy/install-test-tools.sh).

#![allow(dead_code)] // each test binary uses a part

use std::path::PathBuf;
use std::process::{Command, Stdio};
use std::sync::OnceLock;

pub const ADMIN: &str = "cubecal_admin";
pub const PASSWORD: &str = "throw-away test password";

#[derive(Debug)]
pub struct Cluster {
    pub port: u16,
    pub dir: PathBuf,
    pub password_file: PathBuf,
    bindir: PathBuf,
    as_postgres: bool,
    /// The server options `pg_ctl start -o` was given (for a restart).
    options: String,
}

fn tools_required() -> bool {
    std::env::var("CUBECAL_REQUIRE_TOOLS").is_ok_and(|v| v == "1")
}

/// The newest `/usr/lib/postgresql/N/bin` with `initdb`, or `CUBECAL_PG_BINDIR`.
fn bindir() -> Option<PathBuf> {
    if let Some(d) = std::env::var_os("CUBECAL_PG_BINDIR") {
        return Some(PathBuf::from(d));
    }
    let mut found: Vec<(u32, PathBuf)> = std::fs::read_dir("/usr/lib/postgresql")
        .ok()?
        .flatten()
        .filter_map(|e| {
            let v: u32 = e.file_name().to_str()?.parse().ok()?;
            let bin = e.path().join("bin");
            bin.join("initdb").is_file().then_some((v, bin))
        })
        .collect();
    found.sort();
    found.pop().map(|(_, b)| b)
}

fn is_root() -> bool {
    Command::new("id")
        .arg("-u")
        .output()
        .is_ok_and(|o| String::from_utf8_lossy(&o.stdout).trim() == "0")
}

impl Cluster {
    fn tool(&self, name: &str) -> Command {
        let exe = self.bindir.join(name);
        if self.as_postgres {
            let mut c = Command::new("runuser");
            c.args(["-u", "postgres", "--"]).arg(exe);
            c
        } else {
            Command::new(exe)
        }
    }

    /// `durable`: fsync and full-page writes on, as a production server runs (the benchmark);
    /// otherwise off, for quick tests.
    fn start(durable: bool) -> Result<Cluster, String> {
        let bindir = bindir().ok_or("no PostgreSQL server (initdb) under /usr/lib/postgresql")?;
        let as_postgres = is_root();
        let dir = tempfile::Builder::new()
            .prefix("cubecal-pg-")
            .tempdir()
            .map_err(|e| format!("temp dir: {e}"))?
            .keep();
        let password_file = dir.join("password");
        std::fs::write(&password_file, format!("{PASSWORD}\n")).map_err(|e| e.to_string())?;
        if as_postgres {
            let ok = Command::new("chown")
                .args(["-R", "postgres:postgres"])
                .arg(&dir)
                .status()
                .is_ok_and(|s| s.success());
            if !ok {
                return Err(format!("cannot chown {} to postgres", dir.display()));
            }
        }
        let port = std::net::TcpListener::bind("127.0.0.1:0")
            .and_then(|l| l.local_addr())
            .map_err(|e| e.to_string())?
            .port();
        let mut options = format!(
            "-p {port} -k {} -c listen_addresses=127.0.0.1 -c max_connections=200",
            dir.display()
        );
        if !durable {
            options += " -c fsync=off -c full_page_writes=off";
        }
        let cluster = Cluster {
            port,
            dir: dir.clone(),
            password_file,
            bindir,
            as_postgres,
            options,
        };
        cluster.watchdog();
        let data = dir.join("data");
        let out = cluster
            .tool("initdb")
            .arg("-D")
            .arg(&data)
            .args([
                "-U",
                ADMIN,
                "-A",
                "scram-sha-256",
                "--no-sync",
                "-E",
                "UTF8",
            ])
            .args(["--locale", "C"])
            .arg(format!("--pwfile={}", cluster.password_file.display()))
            .output()
            .map_err(|e| format!("initdb: {e}"))?;
        if !out.status.success() {
            return Err(format!(
                "initdb failed: {}",
                String::from_utf8_lossy(&out.stderr)
            ));
        }
        cluster.pg_start()?;
        Ok(cluster)
    }

    /// `pg_ctl start` and wait until the server accepts connections.
    fn pg_start(&self) -> Result<(), String> {
        let out = self
            .tool("pg_ctl")
            .arg("-D")
            .arg(self.dir.join("data"))
            .arg("-l")
            .arg(self.dir.join("log"))
            .args(["-w", "-t", "60", "-o", &self.options, "start"])
            .stdout(Stdio::null())
            .output()
            .map_err(|e| format!("pg_ctl: {e}"))?;
        if !out.status.success() {
            let log = std::fs::read_to_string(self.dir.join("log")).unwrap_or_default();
            return Err(format!("pg_ctl start failed: {log}"));
        }
        Ok(())
    }

    /// A cluster of the caller's own (not this binary's shared one), for a test that kills it.
    #[allow(clippy::print_stderr)]
    pub fn own() -> Option<Cluster> {
        match Cluster::start(false) {
            Ok(c) => Some(c),
            Err(reason) => {
                assert!(!tools_required(), "CUBECAL_REQUIRE_TOOLS=1 but {reason}");
                eprintln!("skipped: {reason} (install postgresql: deploy/install-test-tools.sh)");
                None
            }
        }
    }

    /// The server's processes (the postmaster, from `postmaster.pid`, and its children) killed with
    /// SIGKILL at once, as the kernel's OOM killer or a power cut ends them: no shutdown, no
    /// checkpoint. Returns the pids killed.
    pub fn kill(&self) -> Vec<u32> {
        let pidfile = self.dir.join("data/postmaster.pid");
        let text = std::fs::read_to_string(&pidfile)
            .unwrap_or_else(|e| panic!("{}: {e}", pidfile.display()));
        let postmaster: u32 = text
            .lines()
            .next()
            .and_then(|l| l.trim().parse().ok())
            .unwrap_or_else(|| panic!("{}: no pid", pidfile.display()));
        let mut pids = vec![postmaster];
        for entry in std::fs::read_dir("/proc").into_iter().flatten().flatten() {
            let Ok(pid) = entry.file_name().to_string_lossy().parse::<u32>() else {
                continue;
            };
            // /proc/PID/stat: "pid (comm) state ppid …"; comm may hold spaces, so split after ')'
            let ppid = std::fs::read_to_string(entry.path().join("stat"))
                .ok()
                .and_then(|s| {
                    let rest = s.rsplit_once(')')?.1.to_string();
                    rest.split_whitespace().nth(1)?.parse::<u32>().ok()
                });
            if ppid == Some(postmaster) {
                pids.push(pid);
            }
        }
        let status = Command::new("kill")
            .arg("-KILL")
            .args(pids.iter().map(|p| p.to_string()))
            .status()
            .unwrap_or_else(|e| panic!("kill: {e}"));
        assert!(status.success(), "kill -KILL {pids:?} failed");
        // wait until the postmaster is gone (its port closed)
        for _ in 0..100 {
            if !std::path::Path::new(&format!("/proc/{postmaster}")).exists()
                || std::fs::read_to_string(format!("/proc/{postmaster}/stat")).is_ok_and(|s| {
                    s.rsplit_once(')')
                        .is_some_and(|(_, r)| r.trim_start().starts_with('Z'))
                })
            {
                break;
            }
            std::thread::sleep(std::time::Duration::from_millis(50));
        }
        pids
    }

    /// Start the server again after [`Cluster::kill`] (PostgreSQL recovers from its WAL); retried while
    /// the killed processes' shared memory is still being released.
    pub fn restart(&self) {
        let mut last = String::new();
        for _ in 0..20 {
            match self.pg_start() {
                Ok(()) => return,
                Err(e) => last = e,
            }
            std::thread::sleep(std::time::Duration::from_millis(250));
        }
        panic!("restarting the cluster: {last}");
    }

    /// A shell that waits for this process to end, then stops the cluster and removes its directory.
    fn watchdog(&self) {
        let script = r#"while kill -0 "$1" 2>/dev/null; do sleep 1; done
if [ "$4" = yes ]; then runuser -u postgres -- "$2" -D "$3" -m immediate stop; else "$2" -D "$3" -m immediate stop; fi
rm -rf "$5""#;
        let _ = Command::new("sh")
            .arg("-c")
            .arg(script)
            .arg("watchdog")
            .arg(std::process::id().to_string())
            .arg(self.bindir.join("pg_ctl"))
            .arg(self.dir.join("data"))
            .arg(if self.as_postgres { "yes" } else { "no" })
            .arg(&self.dir)
            .stdin(Stdio::null())
            .stdout(Stdio::null())
            .stderr(Stdio::null())
            .spawn();
    }

    /// `postgres://ADMIN@127.0.0.1:PORT/db` (no password: it is in [`Cluster::password_file`]).
    pub fn url(&self, db: &str) -> String {
        format!("postgres://{ADMIN}@127.0.0.1:{}/{db}", self.port)
    }

    /// A superuser connection to `db`.
    pub fn admin(&self, db: &str) -> postgres::Client {
        let mut config: postgres::Config =
            self.url(db).parse().unwrap_or_else(|e| panic!("url: {e}"));
        config.password(PASSWORD);
        config
            .connect(postgres::NoTls)
            .unwrap_or_else(|e| panic!("connecting to {db}: {e:?}"))
    }

    /// A fresh, empty database `name` (a test's own; dropped first if a previous run left it).
    pub fn database(&self, name: &str) -> String {
        assert!(name.chars().all(|c| c.is_ascii_lowercase() || c == '_'));
        // CREATE DATABASE copies template1 and fails while another copy of it is under way
        static CREATING: std::sync::Mutex<()> = std::sync::Mutex::new(());
        let _one_at_a_time = CREATING.lock().unwrap_or_else(|p| p.into_inner());
        let mut admin = self.admin("postgres");
        // two statements: DROP/CREATE DATABASE cannot run in one (implicitly transactional) batch
        for sql in [
            format!("DROP DATABASE IF EXISTS {name}"),
            format!("CREATE DATABASE {name}"),
        ] {
            admin
                .batch_execute(&sql)
                .unwrap_or_else(|e| panic!("{sql}: {e:?}"));
        }
        self.url(name)
    }
}

/// The cluster of this test binary (fsync off), or `None` (with a message) when PostgreSQL is not
/// installed and `CUBECAL_REQUIRE_TOOLS` is not 1.
pub fn cluster() -> Option<&'static Cluster> {
    cluster_with(false)
}

/// [`cluster`], durable (fsync on) when the first caller of this binary asks so.
#[allow(clippy::print_stderr)]
pub fn cluster_with(durable: bool) -> Option<&'static Cluster> {
    static CLUSTER: OnceLock<Result<Cluster, String>> = OnceLock::new();
    match CLUSTER.get_or_init(|| Cluster::start(durable)) {
        Ok(c) => Some(c),
        Err(reason) => {
            assert!(!tools_required(), "CUBECAL_REQUIRE_TOOLS=1 but {reason}");
            eprintln!("skipped: {reason} (install postgresql: deploy/install-test-tools.sh)");
            None
        }
    }
}
