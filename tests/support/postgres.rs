//! A throwaway PostgreSQL server for the job-store tests and the one-machine cluster test:
//! Debian's `postgresql` package (scripts/setup installs it), a cluster made by `initdb` in a
//! temporary directory, listening only on a Unix socket there, stopped (`pg_ctl stop -m
//! immediate`) and removed when dropped. As root (CI machines) the server runs as the package's
//! `postgres` user: `initdb` refuses root.

use std::path::{Path, PathBuf};
use std::process::Command;

use crate::missing;

/// See the module documentation.
pub struct TempPostgres {
    dir: tempfile::TempDir,
    bin: PathBuf,
    root: bool,
}

/// Debian installs one directory of server programs per major version.
fn server_programs() -> Option<PathBuf> {
    let mut versions: Vec<PathBuf> = std::fs::read_dir("/usr/lib/postgresql")
        .ok()?
        .flatten()
        .map(|e| e.path().join("bin"))
        .filter(|bin| bin.join("initdb").exists())
        .collect();
    versions.sort();
    versions.pop()
}

/// `program` of the server, as the `postgres` user when we are root.
fn server_command(bin: &Path, root: bool, program: &str) -> Command {
    if root {
        let mut command = Command::new("runuser");
        command
            .args(["-u", "postgres", "--"])
            .arg(bin.join(program));
        command
    } else {
        Command::new(bin.join(program))
    }
}

impl TempPostgres {
    /// Starts one, or says why it cannot (a failure under CI, a skip elsewhere).
    pub fn start() -> Option<Self> {
        let Some(bin) = server_programs() else {
            return missing("PostgreSQL must be installed (scripts/setup: postgresql)");
        };
        let dir = tempfile::tempdir().unwrap();
        let root = Command::new("id")
            .arg("-u")
            .output()
            .is_ok_and(|o| o.stdout.trim_ascii() == b"0");
        if root {
            let _ = Command::new("chown")
                .arg("postgres")
                .arg(dir.path())
                .status();
        }
        let postgres = Self { dir, bin, root };
        let data = postgres.data();
        postgres.run(
            "initdb",
            &[
                "-D".as_ref(),
                data.as_os_str(),
                "-U".as_ref(),
                "c4g".as_ref(),
                "--auth=trust".as_ref(),
                "--no-sync".as_ref(),
            ],
        );
        postgres.resume();
        Some(postgres)
    }

    /// Runs one of the server's programs, which must succeed.
    fn run(&self, program: &str, args: &[&std::ffi::OsStr]) {
        let out = server_command(&self.bin, self.root, program)
            .args(args)
            .output()
            .unwrap();
        assert!(
            out.status.success(),
            "{program}: {}{}",
            String::from_utf8_lossy(&out.stderr),
            self.log()
        );
    }

    /// Stops the server (connections are cut), keeping its data: an outage.
    pub fn pause(&self) {
        let data = self.data();
        self.run(
            "pg_ctl",
            &[
                "-D".as_ref(),
                data.as_os_str(),
                "-m".as_ref(),
                "fast".as_ref(),
                "-w".as_ref(),
                "stop".as_ref(),
            ],
        );
    }

    /// Starts the server on its data (after [`pause`](Self::pause)), waiting until it answers.
    pub fn resume(&self) {
        let options = format!(
            "-c listen_addresses='' -c unix_socket_directories='{}' -c fsync=off",
            self.dir.path().display()
        );
        let (data, log) = (self.data(), self.dir.path().join("log"));
        self.run(
            "pg_ctl",
            &[
                "-D".as_ref(),
                data.as_os_str(),
                "-o".as_ref(),
                options.as_ref(),
                "-w".as_ref(),
                "-l".as_ref(),
                log.as_os_str(),
                "start".as_ref(),
            ],
        );
    }

    /// A URL for `C4G_JOB_DATABASE`: user `c4g`, database `postgres`, over the socket.
    pub fn url(&self) -> String {
        format!(
            "postgres://c4g@localhost/postgres?host={}",
            self.dir.path().display()
        )
    }

    fn data(&self) -> PathBuf {
        self.dir.path().join("data")
    }

    /// The server's log.
    pub fn log(&self) -> String {
        std::fs::read_to_string(self.dir.path().join("log")).unwrap_or_default()
    }
}

impl Drop for TempPostgres {
    fn drop(&mut self) {
        let _ = server_command(&self.bin, self.root, "pg_ctl")
            .arg("-D")
            .arg(self.data())
            .args(["-m", "immediate", "stop"])
            .output();
    }
}
