//! The sample's `report.html` in a real headless browser (Chromium): it renders, and every image
//! on it decodes. `PRESTON_CHROMIUM` names the browser, else `chromium`, `chromium-browser` or
//! `google-chrome` on the PATH. Without one the test fails when `PRESTON_REQUIRE_BROWSER` is set
//! (CI sets it and installs Chromium, `.ci/run`) and says it was skipped otherwise.

mod common;

use common::{data, preston_cmd};
use std::path::PathBuf;
use std::process::Command;

fn browser() -> Option<PathBuf> {
    if let Some(p) = std::env::var_os("PRESTON_CHROMIUM") {
        return Some(PathBuf::from(p));
    }
    let path = std::env::var_os("PATH")?;
    for name in ["chromium", "chromium-browser", "google-chrome"] {
        for dir in std::env::split_paths(&path) {
            let p = dir.join(name);
            if p.is_file() {
                return Some(p);
            }
        }
    }
    None
}

fn headless(browser: &PathBuf) -> Command {
    let mut c = Command::new(browser);
    c.args([
        "--headless",
        "--no-sandbox",
        "--disable-gpu",
        "--disable-dev-shm-usage",
        "--hide-scrollbars",
        "--no-first-run",
        "--allow-file-access-from-files",
    ]);
    c
}

#[test]
fn sample_report_renders_in_chromium_with_every_image() {
    report_renders_with_every_image(&[]);
}

/// With SVG figures, every embedded SVG decodes in the browser as the PNGs do.
#[test]
fn sample_report_with_svg_figures_renders_in_chromium_with_every_image() {
    report_renders_with_every_image(&["--plot-format", "svg"]);
}

/// Solves the sample job with `--report` and `extra` flags, then loads its report.html in
/// Chromium: every image decodes, and a screenshot of the page is not blank.
fn report_renders_with_every_image(extra: &[&str]) {
    let Some(chromium) = browser() else {
        if std::env::var_os("PRESTON_REQUIRE_BROWSER").is_some() {
            panic!("no Chromium found (PRESTON_REQUIRE_BROWSER is set): install it or set PRESTON_CHROMIUM");
        }
        eprintln!("SKIPPED: no Chromium on the PATH; set PRESTON_REQUIRE_BROWSER=1 to make this a failure");
        return;
    };
    let out = tempfile::tempdir().unwrap();
    let o = preston_cmd()
        .args(["solve", "--job"])
        .arg(data("job_point_1mm.toml"))
        .args(extra)
        .args(["--report", "--out"])
        .arg(out.path())
        .output()
        .unwrap();
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    let page = out.path().join("report.html");
    let url = format!("file://{}", page.display());
    let html = std::fs::read_to_string(&page).unwrap();
    let images = html.matches("<img ").count();
    assert!(images >= 8, "{images} images");
    let svg_images = html.matches("src=\"data:image/svg+xml;base64,").count();
    if extra.contains(&"svg") {
        assert_eq!(svg_images, images, "every figure is an SVG");
    } else {
        assert_eq!(svg_images, 0, "every figure is a PNG");
    }
    // The DOM once the page has loaded: its script has counted the images that decoded.
    let dom = headless(&chromium)
        .args(["--virtual-time-budget=10000", "--dump-dom"])
        .arg(&url)
        .output()
        .unwrap();
    assert!(
        dom.status.success(),
        "{}",
        String::from_utf8_lossy(&dom.stderr)
    );
    let dom = String::from_utf8_lossy(&dom.stdout);
    let expected = format!("data-images-loaded=\"{images}\" data-images-total=\"{images}\"");
    assert!(
        dom.contains(&expected),
        "not every image loaded: {}",
        dom.lines()
            .find(|l| l.contains("<body"))
            .unwrap_or("no <body>")
    );
    // A screenshot of the page: written, of the window's size, and not blank.
    let shot = std::env::var_os("PRESTON_SCREENSHOT")
        .map(PathBuf::from)
        .unwrap_or_else(|| out.path().join("report.png"));
    let o = headless(&chromium)
        .args(["--window-size=1280,4000", "--virtual-time-budget=10000"])
        .arg(format!("--screenshot={}", shot.display()))
        .arg(&url)
        .output()
        .unwrap();
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    let decoder = png::Decoder::new(std::fs::File::open(&shot).unwrap());
    let mut reader = decoder.read_info().unwrap();
    let mut buf = vec![0; reader.output_buffer_size()];
    let info = reader.next_frame(&mut buf).unwrap();
    assert_eq!((info.width, info.height), (1280, 4000));
    let bpp = info.color_type.samples();
    let mut colours: Vec<&[u8]> = buf[..info.buffer_size()].chunks(bpp).collect();
    colours.sort();
    colours.dedup();
    assert!(
        colours.len() > 200,
        "{} colours: a blank page?",
        colours.len()
    );
}
