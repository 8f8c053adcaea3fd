//! The sample's figures (`preston solve --job data/job.toml --plots`), read back as pixels: every
//! axis line has background between it (or its tick marks) and its tick labels (no label touches or crosses
//! a frame or a colour bar's baseline), tick labels stand apart from each other, and every axis
//! with numbers has at least three of them.

mod common;

use common::{data, preston_cmd};
use std::path::Path;

/// A channel value at or below which a pixel is drawn ink (axis lines and text are black).
const DARK_LEVEL: u8 = 64;
/// A channel value above which, in every channel, a pixel is background (white canvas).
const BACKGROUND_LEVEL: u8 = 235;
/// Shortest axis line looked for, as a share of the canvas side.
const AXIS_SHARE: f64 = 0.25;
/// Background pixels required, in every row (column) along an axis line, between the line (or
/// its tick mark) and what lies beyond: the tick labels.
const GAP_PX: usize = 2;
/// Longest tick mark: a dark run from the axis line outwards, pixels.
const TICK_MAX_PX: usize = 6;
/// Depth of the band beside an axis where its tick labels are, pixels.
const LABEL_BAND_PX: usize = 22;
/// Background columns that separate two tick labels of a horizontal axis.
const LABEL_SPACING_PX: usize = 6;
/// Widest single tick label, pixels: two labels drawn over each other make a wider blob.
const LABEL_MAX_WIDTH_PX: usize = 90;
/// Fewest tick labels on a horizontal axis.
const MIN_TICK_LABELS: usize = 3;

/// A decoded RGB image.
struct Image {
    w: usize,
    h: usize,
    rgb: Vec<u8>,
}

impl Image {
    fn open(path: &Path) -> Image {
        let decoder = png::Decoder::new(std::fs::File::open(path).unwrap());
        let mut reader = decoder.read_info().unwrap();
        let mut buf = vec![0; reader.output_buffer_size()];
        let info = reader.next_frame(&mut buf).unwrap();
        let bpp = info.color_type.samples();
        let rgb = buf[..info.buffer_size()]
            .chunks(bpp)
            .flat_map(|p| [p[0], p[1], p[2]])
            .collect();
        Image {
            w: info.width as usize,
            h: info.height as usize,
            rgb,
        }
    }

    fn px(&self, x: usize, y: usize) -> [u8; 3] {
        let k = 3 * (y * self.w + x);
        [self.rgb[k], self.rgb[k + 1], self.rgb[k + 2]]
    }

    fn dark(&self, x: usize, y: usize) -> bool {
        self.px(x, y).iter().all(|c| *c <= DARK_LEVEL)
    }

    fn background(&self, x: usize, y: usize) -> bool {
        self.px(x, y).iter().all(|c| *c > BACKGROUND_LEVEL)
    }
}

/// A straight run of dark pixels: the fixed coordinate and the span along the run.
#[derive(Debug, Clone, Copy)]
struct Line {
    at: usize,
    from: usize,
    to: usize,
}

/// The longest dark run along `n` pixels where `dark(k)` says whether pixel `k` is dark.
fn longest_run(n: usize, dark: impl Fn(usize) -> bool) -> (usize, usize) {
    let (mut best, mut start) = ((0, 0), None);
    for k in 0..=n {
        match (k < n && dark(k), start) {
            (true, None) => start = Some(k),
            (false, Some(s)) => {
                if k - s > best.1 - best.0 {
                    best = (s, k);
                }
                start = None;
            }
            _ => {}
        }
    }
    best
}

/// Vertical axis lines: columns in the left third (where the y axes are; the data beyond may hold
/// black clipped points) whose longest dark run is at least [`AXIS_SHARE`] of the height and
/// longer than the run of the column left of it (one line per axis).
fn vertical_axes(img: &Image) -> Vec<Line> {
    let runs: Vec<(usize, usize)> = (0..img.w / 3)
        .map(|x| longest_run(img.h, |y| img.dark(x, y)))
        .collect();
    let len = |x: usize| runs[x].1 - runs[x].0;
    (0..img.w / 3)
        .filter(|&x| len(x) as f64 >= AXIS_SHARE * img.h as f64)
        .filter(|&x| x == 0 || len(x - 1) < len(x))
        .map(|x| Line {
            at: x,
            from: runs[x].0,
            to: runs[x].1,
        })
        .collect()
}

/// Horizontal axis lines, as [`vertical_axes`] for the rows of the lower half (the x axes and
/// the colour bar's baseline).
fn horizontal_axes(img: &Image) -> Vec<Line> {
    let runs: Vec<(usize, usize)> = (0..img.h)
        .map(|y| longest_run(img.w, |x| img.dark(x, y)))
        .collect();
    let len = |y: usize| runs[y].1 - runs[y].0;
    (img.h / 2..img.h)
        .filter(|&y| len(y) as f64 >= AXIS_SHARE * img.w as f64)
        .filter(|&y| y == 0 || len(y - 1) < len(y))
        .map(|y| Line {
            at: y,
            from: runs[y].0,
            to: runs[y].1,
        })
        .collect()
}

/// The first position along an axis line (of `span`) where its outside is not clear: past the
/// line, at `at`, on the side `dir`, a tick mark (a dark run of at most [`TICK_MAX_PX`]) may
/// follow, then [`GAP_PX`] background pixels must. `pixel(across, along)` reads (dark, background).
fn first_crowded(
    at: usize,
    dir: isize,
    limit: usize,
    span: std::ops::Range<usize>,
    pixel: impl Fn(usize, usize) -> (bool, bool),
) -> Option<usize> {
    let step = |d: usize| {
        let c = at as isize + dir * d as isize;
        (c >= 0 && (c as usize) < limit).then_some(c as usize)
    };
    span.into_iter().find(|&k| {
        let mut tick = 0;
        while tick < TICK_MAX_PX && step(tick + 1).is_some_and(|c| pixel(c, k).0) {
            tick += 1;
        }
        !(1..=GAP_PX).all(|g| step(tick + g).is_some_and(|c| pixel(c, k).1))
    })
}

/// The clusters of ink columns in rows `rows` between columns `cols` (at least one non-background
/// pixel), split by [`LABEL_SPACING_PX`] background columns: (first, last) column of each.
fn label_clusters(
    img: &Image,
    rows: std::ops::Range<usize>,
    cols: std::ops::Range<usize>,
) -> Vec<(usize, usize)> {
    let mut out: Vec<(usize, usize)> = Vec::new();
    for x in cols {
        if rows.clone().any(|y| !img.background(x, y)) {
            match out.last_mut() {
                Some(c) if x - c.1 <= LABEL_SPACING_PX => c.1 = x,
                _ => out.push((x, x)),
            }
        }
    }
    out
}

/// The checks of one figure; returns what is wrong with it.
fn layout_faults(path: &Path) -> Vec<String> {
    let img = Image::open(path);
    let name = path.file_name().unwrap().to_string_lossy().to_string();
    let mut faults = Vec::new();
    let verticals = vertical_axes(&img);
    let horizontals = horizontal_axes(&img);
    if verticals.is_empty() && horizontals.is_empty() {
        faults.push(format!("{name}: no axis line found"));
    }
    for a in &verticals {
        // Tick labels left of a vertical axis: background between them and the line.
        let crowded = first_crowded(a.at, -1, img.w, a.from..a.to, |x, y| {
            (img.dark(x, y), img.background(x, y))
        });
        if let Some(y) = crowded {
            faults.push(format!(
                "{name}: a y tick label touches the axis at x = {} (row {y})",
                a.at
            ));
        }
    }
    for a in &horizontals {
        // Tick labels below a horizontal axis (a frame's bottom or a colour bar's baseline).
        let crowded = first_crowded(a.at, 1, img.h, a.from..a.to, |y, x| {
            (img.dark(x, y), img.background(x, y))
        });
        if let Some(x) = crowded {
            faults.push(format!(
                "{name}: an x tick label touches the line at y = {} (column {x})",
                a.at
            ));
        }
        let band = (a.at + 1 + GAP_PX)..(a.at + 1 + LABEL_BAND_PX).min(img.h);
        let cols = a.from.saturating_sub(LABEL_MAX_WIDTH_PX / 2)
            ..(a.to + LABEL_MAX_WIDTH_PX / 2).min(img.w);
        let clusters = label_clusters(&img, band, cols);
        if clusters.len() < MIN_TICK_LABELS {
            faults.push(format!(
                "{name}: {} tick label(s) under the axis at y = {}",
                clusters.len(),
                a.at
            ));
        }
        for c in clusters {
            if c.1 - c.0 + 1 > LABEL_MAX_WIDTH_PX {
                faults.push(format!(
                    "{name}: tick labels run together over columns {}..{} under y = {}",
                    c.0, c.1, a.at
                ));
            }
        }
    }
    faults
}

#[test]
fn the_sample_figures_keep_labels_clear_of_frames_and_of_each_other() {
    let out = tempfile::tempdir().unwrap();
    let o = preston_cmd()
        .args(["solve", "--job"])
        .arg(data("job.toml"))
        .args(["--plots", "--out"])
        .arg(out.path())
        .output()
        .unwrap();
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    let mut checked = 0;
    let mut faults = Vec::new();
    for stem in preston_io::figures::SOLVE_FIGURES {
        let f = out.path().join(format!("{stem}.png"));
        assert!(f.is_file(), "{stem}.png missing");
        faults.extend(layout_faults(&f));
        checked += 1;
    }
    assert_eq!(checked, preston_io::figures::SOLVE_FIGURES.len());
    assert!(faults.is_empty(), "{}", faults.join("\n"));
}
