//! Opens an HTML report in headless Chromium (Debian's `chromium`, which
//! `.ci/run` installs) and says what a reader would miss: images that did not
//! load and script errors on the console.
#![allow(dead_code)]

use std::path::{Path, PathBuf};
use std::process::Command;

/// What the browser saw.
#[derive(Debug)]
pub struct Rendered {
    pub title: String,
    pub images: usize,
    /// `src` of every image that did not load (or decoded to nothing).
    pub broken: Vec<String>,
    /// Smallest natural width of the loaded images, pixels.
    pub min_width: u64,
    /// Console lines with an uncaught error.
    pub script_errors: Vec<String>,
    /// Width of the laid-out page in a 1280 x 800 window, pixels: over 1280, the reader
    /// scrolls sideways.
    pub scroll_width: u64,
    /// Top of the element `id="summary"` in that window, pixels (None: no such element);
    /// under 800, it is on the first screen.
    pub summary_top: Option<f64>,
}

/// The browser: `RANGEGAN_CHROMIUM`, else `chromium` or `chromium-browser` on PATH.
pub fn chromium() -> Option<PathBuf> {
    if let Some(p) = std::env::var_os("RANGEGAN_CHROMIUM") {
        return Some(PathBuf::from(p));
    }
    ["chromium", "chromium-browser"].iter().find_map(|name| {
        std::env::var_os("PATH").and_then(|paths| {
            std::env::split_paths(&paths)
                .map(|d| d.join(name))
                .find(|p| p.is_file())
        })
    })
}

/// Loads `html` in an iframe of a checking page (in `scratch`) and reports
/// what loaded. None when no browser is installed and `RANGEGAN_REQUIRE_BROWSER`
/// is unset (a message says so); with it set, a missing browser fails.
pub fn render(html: &Path, scratch: &Path) -> Option<Rendered> {
    let Some(browser) = chromium() else {
        assert!(
            std::env::var_os("RANGEGAN_REQUIRE_BROWSER").is_none(),
            "RANGEGAN_REQUIRE_BROWSER is set but no chromium was found (apt-get install chromium)"
        );
        eprintln!(
            "skipping the browser check: no chromium (apt-get install chromium; .ci/run does)"
        );
        return None;
    };
    let html = html.canonicalize().expect("report exists");
    let page = scratch.join("browser_check.html");
    let src = format!("file://{}", html.display()).replace('\'', "%27");
    std::fs::write(
        &page,
        format!(
            r#"<!doctype html><html><body><iframe id="f" style="width:1280px;height:800px;border:0" src='{src}'></iframe><script>
const f = document.getElementById('f');
f.onload = () => {{
  const d = f.contentDocument;
  const imgs = [...d.images];
  const broken = imgs.filter(i => !(i.complete && i.naturalWidth > 0)).map(i => i.getAttribute('src'));
  const widths = imgs.filter(i => i.naturalWidth > 0).map(i => i.naturalWidth);
  const summary = d.getElementById('summary');
  const out = document.createElement('pre');
  out.id = 'result';
  out.textContent = JSON.stringify({{title: d.title, images: imgs.length, broken,
    min_width: widths.length ? Math.min(...widths) : 0,
    scroll_width: d.documentElement.scrollWidth,
    summary_top: summary ? summary.getBoundingClientRect().top : null}});
  document.body.appendChild(out);
}};
</script></body></html>"#
        ),
    )
    .unwrap();
    let profile = scratch.join("chromium-profile");
    let out = Command::new(&browser)
        .args([
            "--headless",
            "--no-sandbox",
            "--disable-gpu",
            "--allow-file-access-from-files",
            "--virtual-time-budget=10000",
            "--enable-logging=stderr",
            "--v=0",
            "--dump-dom",
        ])
        .arg(format!("--user-data-dir={}", profile.display()))
        .arg(format!("file://{}", page.display()))
        .output()
        .expect("chromium runs");
    let dom = String::from_utf8_lossy(&out.stdout);
    let log = String::from_utf8_lossy(&out.stderr);
    let json = dom
        .split("<pre id=\"result\">")
        .nth(1)
        .and_then(|s| s.split("</pre>").next())
        .unwrap_or_else(|| panic!("the checking page did not finish:\n{dom}\n{log}"))
        .replace("&amp;", "&")
        .replace("&lt;", "<")
        .replace("&gt;", ">")
        .replace("&quot;", "\"");
    let v: serde_json::Value = serde_json::from_str(&json).expect("result JSON");
    Some(Rendered {
        title: v["title"].as_str().unwrap_or_default().to_string(),
        images: v["images"].as_u64().unwrap_or(0) as usize,
        broken: v["broken"]
            .as_array()
            .map(|a| {
                a.iter()
                    .filter_map(|s| s.as_str().map(String::from))
                    .collect()
            })
            .unwrap_or_default(),
        min_width: v["min_width"].as_u64().unwrap_or(0),
        scroll_width: v["scroll_width"].as_u64().unwrap_or(0),
        summary_top: v["summary_top"].as_f64(),
        script_errors: log
            .lines()
            .filter(|l| l.contains("CONSOLE") && l.contains("Uncaught"))
            .map(String::from)
            .collect(),
    })
}
