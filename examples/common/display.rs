//! Whether the viewer can open a window here: an X11 display that answers
//! (the viewer is built with winit's X11 backend only, which Wayland
//! sessions serve through XWayland). winit panics inside Bevy's plugin build
//! when it cannot connect, so the examples probe first and run headless
//! instead.

use std::time::Duration;

/// `Ok(display)` when `DISPLAY` names an X server that accepts a connection,
/// else why not.
pub fn x11_display() -> Result<String, String> {
    x11_display_at(&std::env::var("DISPLAY").unwrap_or_default())
}

/// [`x11_display`] for a given `DISPLAY` value.
pub fn x11_display_at(display: &str) -> Result<String, String> {
    if display.is_empty() {
        return Err("no display (DISPLAY is unset or empty)".into());
    }
    // `[host]:number[.screen]`, host empty or `unix` for the local socket.
    let parsed = display.rsplit_once(':').and_then(|(host, rest)| {
        let number: u16 = rest.split('.').next()?.parse().ok()?;
        Some((host, number))
    });
    let Some((host, number)) = parsed else {
        return Err(format!(
            "DISPLAY={display:?} is not of the form [host]:number"
        ));
    };
    let reachable = if host.is_empty() || host == "unix" {
        local_socket(number)
    } else {
        use std::net::ToSocketAddrs;
        let port = 6000u16.saturating_add(number);
        (host, port).to_socket_addrs().is_ok_and(|mut addrs| {
            addrs.any(|a| std::net::TcpStream::connect_timeout(&a, Duration::from_secs(2)).is_ok())
        })
    };
    if reachable {
        Ok(display.to_string())
    } else {
        Err(format!("the X display {display:?} does not answer"))
    }
}

#[cfg(unix)]
fn local_socket(number: u16) -> bool {
    use std::os::unix::net::UnixStream;
    let path = format!("/tmp/.X11-unix/X{number}");
    if UnixStream::connect(&path).is_ok() {
        return true;
    }
    // Linux servers also listen on the abstract socket of the same name.
    #[cfg(target_os = "linux")]
    {
        use std::os::linux::net::SocketAddrExt;
        if let Ok(addr) = std::os::unix::net::SocketAddr::from_abstract_name(path.as_bytes()) {
            return UnixStream::connect_addr(&addr).is_ok();
        }
    }
    false
}

#[cfg(not(unix))]
fn local_socket(_number: u16) -> bool {
    true
}
