//! The `c4g` binary as a process: help, and how it reports errors (against a fake server that
//! answers one canned HTTP response, not a c4g server).

#![allow(clippy::unwrap_used, clippy::expect_used)]

use std::io::{Read, Write};
use std::net::TcpListener;
use std::process::{Command, Output};

fn c4g(args: &[&str]) -> Output {
    Command::new(env!("CARGO_BIN_EXE_c4g"))
        .args(args)
        .env_remove("C4G_SERVER")
        .env_remove("C4G_API_KEY")
        .output()
        .unwrap()
}

#[test]
fn help_lists_every_command_and_the_global_flags() {
    let out = c4g(&["--help"]);
    assert!(out.status.success());
    let help = String::from_utf8(out.stdout).unwrap();
    for word in [
        "upload",
        "info",
        "clips",
        "delete",
        "decode",
        "export",
        "render",
        "stream",
        "--server",
        "--api-key",
        "--json",
        "C4G_SERVER",
        "C4G_API_KEY",
    ] {
        assert!(help.contains(word), "--help lacks {word}:\n{help}");
    }
}

#[test]
fn every_subcommand_has_help() {
    for command in [
        "upload", "info", "clips", "delete", "decode", "export", "render", "stream",
    ] {
        let out = c4g(&[command, "--help"]);
        assert!(out.status.success(), "{command} --help failed");
        assert!(!out.stdout.is_empty());
    }
}

#[test]
fn usage_errors_exit_non_zero() {
    assert!(
        !c4g(&["decode", "clip"]).status.success(),
        "--t is required"
    );
    assert!(
        !c4g(&["stream", "clip", "--step", "0.1", "--fps", "10"])
            .status
            .success(),
        "--step and --fps conflict"
    );
    assert!(
        !c4g(&[
            "render", "clip", "--t", "0.5", "--orbit", "30", "-o", "x.mp4"
        ])
        .status
        .success(),
        "--t and a trajectory conflict"
    );
}

#[test]
fn an_api_error_prints_status_kind_and_message() {
    let listener = TcpListener::bind("127.0.0.1:0").unwrap();
    let address = listener.local_addr().unwrap();
    let server = std::thread::spawn(move || {
        let (mut socket, _) = listener.accept().unwrap();
        let mut request = [0u8; 4096];
        let n = socket.read(&mut request).unwrap();
        let body =
            r#"{"error": "no clip abc; list clips with GET /v1/clips", "kind": "not_found"}"#;
        write!(
            socket,
            "HTTP/1.1 404 Not Found\r\ncontent-type: application/json\r\ncontent-length: {}\r\n\
             connection: close\r\n\r\n{body}",
            body.len()
        )
        .unwrap();
        String::from_utf8_lossy(&request[..n]).into_owned()
    });
    let server_url = format!("http://{address}");
    let out = c4g(&["--server", &server_url, "--api-key", "k3y", "info", "abc"]);
    let request = server.join().unwrap();
    assert!(request.starts_with("GET /v1/clips/abc "), "{request}");
    assert!(
        request
            .to_ascii_lowercase()
            .contains("authorization: bearer k3y"),
        "{request}"
    );
    assert!(!out.status.success());
    let stderr = String::from_utf8(out.stderr).unwrap();
    assert_eq!(
        stderr.trim(),
        "error: 404 not_found: no clip abc; list clips with GET /v1/clips"
    );
}

#[test]
fn an_unreachable_server_is_an_error_not_a_panic() {
    // Bind then drop: the port is (almost certainly) closed.
    let address = TcpListener::bind("127.0.0.1:0")
        .unwrap()
        .local_addr()
        .unwrap();
    let out = c4g(&["--server", &format!("http://{address}"), "clips"]);
    assert!(!out.status.success());
    let stderr = String::from_utf8(out.stderr).unwrap();
    assert!(
        stderr.starts_with("error: request to the server failed"),
        "{stderr}"
    );
}
