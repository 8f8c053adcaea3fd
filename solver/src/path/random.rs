//! Pseudo-random unicursal paths: a Hamiltonian cycle on a grid built from a random spanning
//! tree, which breaks up the periodic ridges (mid-spatial-frequency ripple) a raster leaves.
//!
//! Construction (the "maze-walk" cycle): the `2 mx x 2 my` node grid is cut into `mx x my` blocks
//! of 2 x 2 nodes. A uniform random spanning tree of the block grid is drawn by Wilson's
//! algorithm (loop-erased random walks; Wilson 1996). Walking around the tree with a hand on it
//! visits every node exactly once and returns to the start: each block contributes the four
//! sides of its 2 x 2 square, except that a tree edge between two blocks replaces the two facing
//! sides by the two edges that join the squares. Every node then has degree 2, and since the
//! tree is connected and acyclic the union is one cycle through all `4 mx my` nodes.
//!
//! Straight runs of the cycle come from straight chains of tree edges without side branches
//! (a chain of `k + 1` blocks gives a run of `2k + 1` steps along its sides). A run longer than
//! `max_run` is broken by cutting the tree edge nearest its middle and reconnecting the two
//! parts by another block edge chosen at random between them; this repeats until no run is too
//! long. The path is the cycle opened at the grid's first corner.

use super::DwellPath;
use crate::error::{Error, Result};
use crate::map::BoundingBox;
use crate::rng::SplitMix64;
use serde::{Deserialize, Serialize};

/// Settings of [`random_unicursal`].
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct RandomPathSettings {
    /// Grid pitch, mm (also the step length).
    pub pitch_mm: f64,
    /// Seed of the generator.
    pub seed: u64,
    /// Longest straight run allowed, in steps (at least 3).
    pub max_run: usize,
    /// Node jitter as a fraction of the pitch, in [0, 1]: each node moves by independent uniform
    /// offsets in `[-j P / 2, j P / 2]` along x and y (kept inside the region), drawn from a
    /// stream of its own so the cycle of a seed does not change. 0: the plain lattice.
    pub jitter: f64,
}

impl Default for RandomPathSettings {
    fn default() -> Self {
        Self {
            pitch_mm: 1.0,
            seed: 1,
            max_run: 20,
            jitter: 0.0,
        }
    }
}

/// A pseudo-random unicursal path and its grid.
#[derive(Debug, Clone)]
pub struct RandomPath {
    /// The path, one grid node per point, unit (pitch) steps.
    pub path: DwellPath,
    /// Grid nodes visited along x and y (even numbers).
    pub nodes: [usize; 2],
    /// Grid nodes of the region along x and y (one more than `nodes` where that count is odd:
    /// the last column or row is then left out, as a 2 x 2 block construction needs even sides).
    pub region_nodes: [usize; 2],
    /// Longest straight run of the path, steps (of the lattice cycle, before any jitter).
    pub longest_run: usize,
    /// Tree edges exchanged to meet `max_run`.
    pub swaps: usize,
}

/// Most points a random path may have.
const MAX_POINTS: usize = 50_000_000;

/// The block grid's spanning tree: `right[b]` joins block `b` to its +x neighbour, `up[b]` to its
/// +y neighbour (block index `bx + mx * by`).
struct Tree {
    mx: usize,
    my: usize,
    right: Vec<bool>,
    up: Vec<bool>,
}

impl Tree {
    /// Uniform spanning tree by Wilson's algorithm.
    fn wilson(mx: usize, my: usize, rng: &mut SplitMix64) -> Self {
        let n = mx * my;
        let mut t = Tree {
            mx,
            my,
            right: vec![false; n],
            up: vec![false; n],
        };
        let mut in_tree = vec![false; n];
        let mut next = vec![usize::MAX; n];
        in_tree[0] = true;
        for start in 0..n {
            let mut u = start;
            while !in_tree[u] {
                let nb = t.neighbours(u);
                let k = ((rng.uniform() * nb.len() as f64) as usize).min(nb.len() - 1);
                next[u] = nb[k];
                u = nb[k];
            }
            let mut u = start;
            while !in_tree[u] {
                in_tree[u] = true;
                t.set(u, next[u], true);
                u = next[u];
            }
        }
        t
    }

    fn neighbours(&self, b: usize) -> Vec<usize> {
        let (bx, by) = (b % self.mx, b / self.mx);
        let mut v = Vec::with_capacity(4);
        if bx > 0 {
            v.push(b - 1);
        }
        if bx + 1 < self.mx {
            v.push(b + 1);
        }
        if by > 0 {
            v.push(b - self.mx);
        }
        if by + 1 < self.my {
            v.push(b + self.mx);
        }
        v
    }

    /// Sets the edge between adjacent blocks `a` and `b`.
    fn set(&mut self, a: usize, b: usize, on: bool) {
        let (lo, hi) = (a.min(b), a.max(b));
        if hi == lo + 1 {
            self.right[lo] = on;
        } else {
            self.up[lo] = on;
        }
    }

    fn has(&self, a: usize, b: usize) -> bool {
        let (lo, hi) = (a.min(b), a.max(b));
        if hi == lo + 1 {
            self.right[lo]
        } else {
            self.up[lo]
        }
    }

    /// The Hamiltonian cycle on the `2 mx x 2 my` nodes as node indices `x + 2 mx y`.
    fn cycle(&self) -> Vec<usize> {
        let (w, h) = (2 * self.mx, 2 * self.my);
        let blk = |x: usize, y: usize| x / 2 + self.mx * (y / 2);
        // The two cycle neighbours of node (x, y).
        let nbrs = |x: usize, y: usize| -> [usize; 2] {
            let b = blk(x, y);
            let (lx, ly) = (x % 2, y % 2);
            let mut out = [usize::MAX; 2];
            let mut k = 0;
            let mut push = |px: usize, py: usize| {
                if k < 2 {
                    out[k] = px + w * py;
                    k += 1;
                }
            };
            // Horizontal: across the block side (lx = 1 -> +x) or along the square.
            let (bx, by) = (x / 2, y / 2);
            let side_x = if lx == 1 {
                (bx + 1 < self.mx && self.right[b]).then(|| x + 1)
            } else {
                (bx > 0 && self.right[b - 1]).then(|| x - 1)
            };
            let side_y = if ly == 1 {
                (by + 1 < self.my && self.up[b]).then(|| y + 1)
            } else {
                (by > 0 && self.up[b - self.mx]).then(|| y - 1)
            };
            // The square's horizontal edge on this row is open unless a tree edge leaves the
            // block on this row's side (down for ly = 0, up for ly = 1); likewise vertical.
            match side_y {
                Some(ny) => push(x, ny),
                None => push(x ^ 1, y),
            }
            match side_x {
                Some(nx) => push(nx, y),
                None => push(x, y ^ 1),
            }
            out
        };
        let n = w * h;
        let mut order = Vec::with_capacity(n);
        let mut prev = usize::MAX;
        let mut cur = 0usize;
        loop {
            order.push(cur);
            let [a, b] = nbrs(cur % w, cur / w);
            let nxt = if a != prev { a } else { b };
            prev = cur;
            cur = nxt;
            if cur == 0 || order.len() > n {
                break;
            }
        }
        order
    }
}

/// Straight runs of a closed node cycle on a grid of width `w`: `(first index in the cycle,
/// steps)` for each maximal run, in cycle order.
fn runs(cycle: &[usize], w: usize) -> Vec<(usize, usize)> {
    let n = cycle.len();
    let dir = |i: usize| -> (i64, i64) {
        let a = cycle[i];
        let b = cycle[(i + 1) % n];
        (
            (b % w) as i64 - (a % w) as i64,
            (b / w) as i64 - (a / w) as i64,
        )
    };
    let dirs: Vec<(i64, i64)> = (0..n).map(dir).collect();
    // Start at a turn so no run wraps around the end.
    let Some(s) = (0..n).find(|&i| dirs[i] != dirs[(i + n - 1) % n]) else {
        return vec![(0, n)];
    };
    let mut out = Vec::new();
    let mut start = s;
    let mut len = 1;
    for k in 1..n {
        let i = (s + k) % n;
        if dirs[i] == dirs[(i + n - 1) % n] {
            len += 1;
        } else {
            out.push((start, len));
            start = i;
            len = 1;
        }
    }
    out.push((start, len));
    out
}

/// Longest straight run of an open path, in steps.
pub fn longest_run(path: &DwellPath) -> usize {
    let (x, y) = (path.x_mm(), path.y_mm());
    let mut best = 0;
    let mut len = 0;
    let mut last: Option<(f64, f64)> = None;
    for i in 1..path.len() {
        let d = (x[i] - x[i - 1], y[i] - y[i - 1]);
        let n = d.0.hypot(d.1).max(f64::MIN_POSITIVE);
        let u = (d.0 / n, d.1 / n);
        len = match last {
            Some(l) if (l.0 - u.0).abs() < 1e-9 && (l.1 - u.1).abs() < 1e-9 => len + 1,
            _ => 1,
        };
        best = usize::max(best, len);
        last = Some(u);
    }
    best
}

/// A pseudo-random unicursal path over `region` at `pitch_mm` (see the module docs): every node
/// of the region's grid (`floor(extent / pitch) + 1` per side, from the lower corner) once, in
/// one stroke of unit steps, except the last column or row where that count is odd.
pub fn random_unicursal(region: &BoundingBox, settings: &RandomPathSettings) -> Result<RandomPath> {
    let p = settings.pitch_mm;
    check_settings(settings)?;
    let (nx, ny) = (
        grid_nodes(region.x_min_mm, region.x_max_mm, p, "x")?,
        grid_nodes(region.y_min_mm, region.y_max_mm, p, "y")?,
    );
    let (mx, my) = (nx / 2, ny / 2);
    if mx < 2 || my < 2 {
        return Err(Error::invalid(
            "random path region",
            format!(
                "needs at least 4 x 4 grid nodes for a random cycle, got {nx} x {ny} at pitch {p} mm"
            ),
        ));
    }
    if (4 * mx).saturating_mul(my) > MAX_POINTS {
        return Err(Error::invalid(
            "random path region",
            format!("{} x {} nodes exceed {MAX_POINTS}", 2 * mx, 2 * my),
        ));
    }
    let mut rng = SplitMix64::new(settings.seed);
    let mut tree = Tree::wilson(mx, my, &mut rng);
    let w = 2 * mx;
    let max_rounds = 200 + 20 * mx * my;
    let mut swaps = 0;
    let mut cycle;
    let mut round = 0;
    loop {
        cycle = tree.cycle();
        if cycle.len() != 4 * mx * my {
            return Err(Error::Numerical {
                stage: "random path",
                why: format!(
                    "the tree walk closed after {} of {} nodes",
                    cycle.len(),
                    4 * mx * my
                ),
            });
        }
        let long: Vec<(usize, usize)> = runs(&cycle, w)
            .into_iter()
            .filter(|&(_, l)| l > settings.max_run)
            .collect();
        if long.is_empty() {
            break;
        }
        round += 1;
        if round > max_rounds {
            return Err(Error::invalid(
                "max_run",
                format!(
                    "no cycle with straight runs of at most {} steps found after {swaps} tree \
                     edge exchanges; allow longer runs",
                    settings.max_run
                ),
            ));
        }
        for (start, len) in long {
            if exchange_edge(&mut tree, &cycle, (start, len), &mut rng) {
                swaps += 1;
            }
        }
    }
    let (x, y): (Vec<f64>, Vec<f64>) = cycle
        .iter()
        .map(|&c| {
            (
                region.x_min_mm + (c % w) as f64 * p,
                region.y_min_mm + (c / w) as f64 * p,
            )
        })
        .unzip();
    let mut path = DwellPath::new(x, y)?;
    let longest = longest_run(&path);
    if settings.jitter > 0.0 {
        path = jittered(&path, region, settings)?;
    }
    Ok(RandomPath {
        path,
        nodes: [2 * mx, 2 * my],
        region_nodes: [nx, ny],
        longest_run: longest,
        swaps,
    })
}

/// The settings' own checks: a positive pitch, a jitter in [0, 1], runs of at least 3 steps.
fn check_settings(settings: &RandomPathSettings) -> Result<()> {
    let p = settings.pitch_mm;
    if !(p.is_finite() && p > 0.0) {
        return Err(Error::invalid(
            "pitch_mm",
            format!("must be positive, got {p}"),
        ));
    }
    if !(settings.jitter.is_finite() && (0.0..=1.0).contains(&settings.jitter)) {
        return Err(Error::invalid(
            "jitter",
            format!(
                "must be in [0, 1] (a fraction of the pitch), got {}",
                settings.jitter
            ),
        ));
    }
    if settings.max_run < 3 {
        return Err(Error::invalid(
            "max_run",
            format!("must be at least 3 steps, got {}", settings.max_run),
        ));
    }
    Ok(())
}

/// Grid nodes across `[lo, hi]` mm at pitch `p` (`floor(extent / p) + 1`), or an input error
/// for a bad extent or more than [`MAX_POINTS`] nodes.
fn grid_nodes(lo: f64, hi: f64, p: f64, what: &str) -> Result<usize> {
    let w = hi - lo;
    if !(w.is_finite() && w >= 0.0) {
        return Err(Error::invalid(
            "random path region",
            format!("bad {what} extent [{lo}, {hi}] mm"),
        ));
    }
    let steps = (w / p + 1e-9).floor();
    if steps > MAX_POINTS as f64 {
        return Err(Error::invalid(
            "pitch_mm",
            format!("{p} mm gives more than {MAX_POINTS} nodes across {w} mm"),
        ));
    }
    Ok(steps as usize + 1)
}

/// Breaks the straight run of `len` steps from `start` along `cycle`: removes the tree edge it
/// crosses nearest its middle and joins the two components again by a random other edge
/// between them. Returns whether an edge was exchanged.
fn exchange_edge(
    tree: &mut Tree,
    cycle: &[usize],
    (start, len): (usize, usize),
    rng: &mut SplitMix64,
) -> bool {
    let (mx, my) = (tree.mx, tree.my);
    let w = 2 * mx;
    // The block edges crossed by this run: steps from an odd to an even coordinate.
    let n = cycle.len();
    let mut crossings = Vec::new();
    for k in 0..len {
        let a = cycle[(start + k) % n];
        let b = cycle[(start + k + 1) % n];
        let (ax, ay, bx, by) = (a % w, a / w, b % w, b / w);
        let (ba, bb) = (ax / 2 + mx * (ay / 2), bx / 2 + mx * (by / 2));
        if ba != bb && tree.has(ba, bb) {
            crossings.push((k, ba, bb));
        }
    }
    let Some(&(_, ba, bb)) = crossings.iter().min_by_key(|(k, _, _)| k.abs_diff(len / 2)) else {
        return false;
    };
    if !tree.has(ba, bb) {
        return false;
    }
    tree.set(ba, bb, false);
    let side = component(tree, ba);
    let mut cands = Vec::new();
    for u in 0..mx * my {
        if !side[u] {
            continue;
        }
        for v in tree.neighbours(u) {
            let removed = (u == ba && v == bb) || (u == bb && v == ba);
            if !side[v] && !removed {
                cands.push((u, v));
            }
        }
    }
    if cands.is_empty() {
        tree.set(ba, bb, true);
        return false;
    }
    let k = ((rng.uniform() * cands.len() as f64) as usize).min(cands.len() - 1);
    tree.set(cands[k].0, cands[k].1, true);
    true
}

/// `path` with each node moved by up to half the jitter times the pitch along x and y (its own
/// generator seeded from the path's seed), clamped to `region`.
fn jittered(
    path: &DwellPath,
    region: &BoundingBox,
    settings: &RandomPathSettings,
) -> Result<DwellPath> {
    let mut jr = SplitMix64::new(settings.seed ^ 0x6a09_e667_f3bc_c909);
    let h = 0.5 * settings.jitter * settings.pitch_mm;
    let (x, y): (Vec<f64>, Vec<f64>) = path
        .x_mm()
        .iter()
        .zip(path.y_mm())
        .map(|(&x, &y)| {
            let dx = h * (2.0 * jr.uniform() - 1.0);
            let dy = h * (2.0 * jr.uniform() - 1.0);
            (
                (x + dx).clamp(region.x_min_mm, region.x_max_mm),
                (y + dy).clamp(region.y_min_mm, region.y_max_mm),
            )
        })
        .unzip();
    DwellPath::new(x, y)
}

/// Blocks reachable from `b` in the tree.
fn component(t: &Tree, b: usize) -> Vec<bool> {
    let mut seen = vec![false; t.mx * t.my];
    let mut stack = vec![b];
    seen[b] = true;
    while let Some(u) = stack.pop() {
        for v in t.neighbours(u) {
            if !seen[v] && t.has(u, v) {
                seen[v] = true;
                stack.push(v);
            }
        }
    }
    seen
}

#[cfg(test)]
mod tests {
    use super::*;

    fn region(w: f64, h: f64) -> BoundingBox {
        BoundingBox {
            x_min_mm: -w / 2.0,
            x_max_mm: w / 2.0,
            y_min_mm: -h / 2.0,
            y_max_mm: h / 2.0,
        }
    }

    /// Hamiltonian-path property: every node of the even grid exactly once, unit steps, the
    /// end one step from the start (a cycle), and no straight run above `max_run`.
    fn check(r: &RandomPath, reg: &BoundingBox, p: f64, max_run: usize) {
        let [nx, ny] = r.nodes;
        let path = &r.path;
        assert_eq!(path.len(), nx * ny);
        let mut seen = vec![false; nx * ny];
        for (x, y) in path.x_mm().iter().zip(path.y_mm()) {
            let i = ((x - reg.x_min_mm) / p).round();
            let j = ((y - reg.y_min_mm) / p).round();
            assert!((x - reg.x_min_mm - i * p).abs() < 1e-9);
            assert!((y - reg.y_min_mm - j * p).abs() < 1e-9);
            let (i, j) = (i as usize, j as usize);
            assert!(i < nx && j < ny);
            assert!(!seen[i + nx * j], "node ({i}, {j}) visited twice");
            seen[i + nx * j] = true;
        }
        assert!(seen.iter().all(|&s| s));
        for d in path.ds_mm() {
            assert!((d - p).abs() < 1e-9, "step {d}");
        }
        let n = path.len();
        let close =
            (path.x_mm()[n - 1] - path.x_mm()[0]).hypot(path.y_mm()[n - 1] - path.y_mm()[0]);
        assert!((close - p).abs() < 1e-9);
        assert!(r.longest_run <= max_run, "{} > {max_run}", r.longest_run);
        assert_eq!(longest_run(path), r.longest_run);
    }

    #[test]
    fn random_path_is_hamiltonian_with_bounded_runs() {
        for (w, h, p, seed, max_run) in [
            (60.0, 60.0, 1.0, 1, 20),
            (20.0, 9.0, 0.5, 7, 8),
            (7.0, 30.0, 1.0, 3, 5),
        ] {
            let reg = region(w, h);
            let s = RandomPathSettings {
                pitch_mm: p,
                seed,
                max_run,
                jitter: 0.0,
            };
            let r = random_unicursal(&reg, &s).unwrap();
            check(&r, &reg, p, max_run);
            // Odd node counts lose one boundary column or row, even ones none.
            for k in 0..2 {
                assert!(r.region_nodes[k] - r.nodes[k] == r.region_nodes[k] % 2);
            }
        }
    }

    #[test]
    fn random_path_is_reproducible_and_seeded() {
        let reg = region(30.0, 30.0);
        let s = RandomPathSettings::default();
        let a = random_unicursal(&reg, &s).unwrap();
        let b = random_unicursal(&reg, &s).unwrap();
        assert_eq!(a.path, b.path);
        let c = random_unicursal(&reg, &RandomPathSettings { seed: 2, ..s }).unwrap();
        assert_ne!(a.path, c.path);
    }

    #[test]
    fn unconstrained_runs_exceed_a_tight_limit_and_swaps_fix_them() {
        // Without the run limit (max_run as large as the grid) long runs occur: the boundary
        // sides alone give runs; with a tight limit they are broken by tree edge exchanges.
        let reg = region(40.0, 40.0);
        let free = random_unicursal(
            &reg,
            &RandomPathSettings {
                max_run: 1000,
                ..RandomPathSettings::default()
            },
        )
        .unwrap();
        assert_eq!(free.swaps, 0);
        let tight = random_unicursal(
            &reg,
            &RandomPathSettings {
                max_run: 6,
                ..RandomPathSettings::default()
            },
        )
        .unwrap();
        assert!(free.longest_run > 6, "{}", free.longest_run);
        check(&tight, &reg, 1.0, 6);
        assert!(tight.swaps > 0);
    }

    #[test]
    fn bad_settings_are_refused() {
        let reg = region(10.0, 10.0);
        for s in [
            RandomPathSettings {
                pitch_mm: 0.0,
                ..RandomPathSettings::default()
            },
            RandomPathSettings {
                max_run: 2,
                ..RandomPathSettings::default()
            },
            RandomPathSettings {
                pitch_mm: 4.0,
                ..RandomPathSettings::default()
            },
        ] {
            assert!(random_unicursal(&reg, &s).is_err(), "{s:?}");
        }
    }

    #[test]
    fn jitter_moves_nodes_within_its_bound_and_keeps_the_cycle() {
        let reg = region(20.0, 20.0);
        let plain = random_unicursal(&reg, &RandomPathSettings::default()).unwrap();
        let j = RandomPathSettings {
            jitter: 0.6,
            ..RandomPathSettings::default()
        };
        let a = random_unicursal(&reg, &j).unwrap();
        let b = random_unicursal(&reg, &j).unwrap();
        assert_eq!(a.path.x_mm(), b.path.x_mm());
        assert_eq!(a.path.len(), plain.path.len());
        let h = 0.5 * 0.6 * 1.0;
        let mut moved = 0.0f64;
        for k in 0..a.path.len() {
            let (dx, dy) = (
                a.path.x_mm()[k] - plain.path.x_mm()[k],
                a.path.y_mm()[k] - plain.path.y_mm()[k],
            );
            assert!(dx.abs() <= h + 1e-12 && dy.abs() <= h + 1e-12);
            moved = moved.max(dx.abs());
            assert!((-10.0..=10.0).contains(&a.path.x_mm()[k]));
            assert!((-10.0..=10.0).contains(&a.path.y_mm()[k]));
        }
        assert!(moved > 0.5 * h);
        assert!(random_unicursal(
            &reg,
            &RandomPathSettings {
                jitter: 1.5,
                ..RandomPathSettings::default()
            }
        )
        .is_err());
    }

    /// `integral of exp(-2 pi i x / P) ds` over the segment `a b` (real, imaginary), mm.
    fn segment_coefficient(a: [f64; 2], b: [f64; 2], p: f64) -> (f64, f64) {
        let l = (b[0] - a[0]).hypot(b[1] - a[1]);
        let phi = 2.0 * std::f64::consts::PI * (b[0] - a[0]) / p;
        let ph = -2.0 * std::f64::consts::PI * a[0] / p;
        // l e^{i ph} (e^{-i phi} - 1) / (-i phi), or l e^{i ph} when phi = 0.
        let (fr, fi) = if phi.abs() < 1e-12 {
            (1.0, 0.0)
        } else {
            (phi.sin() / phi, (phi.cos() - 1.0) / phi)
        };
        (
            l * (ph.cos() * fr - ph.sin() * fi),
            l * (ph.cos() * fi + ph.sin() * fr),
        )
    }

    /// `|sum over the path's segments of the integral of exp(-2 pi i x / P) ds|`: the Fourier
    /// coefficient at the pitch frequency along x of the path's line measure (the ripple along
    /// x a constant-feed sweep leaves, up to the TIF's transform), mm.
    fn pitch_coefficient_x(path: &DwellPath, p: f64) -> f64 {
        let (x, y) = (path.x_mm(), path.y_mm());
        let (mut re, mut im) = (0.0, 0.0);
        for k in 1..x.len() {
            let (r, i) = segment_coefficient([x[k - 1], y[k - 1]], [x[k], y[k]], p);
            re += r;
            im += i;
        }
        re.hypot(im)
    }

    #[test]
    fn lattice_paths_keep_the_pitch_ripple_and_jitter_lowers_it() {
        // On the lattice every step along x spans one period and contributes nothing; every
        // step along y sits at a multiple of P and contributes P in phase: the coefficient is
        // P times the number of y steps, whatever their order (a raster along y has them all).
        let reg = region(40.0, 40.0);
        let plain = random_unicursal(&reg, &RandomPathSettings::default()).unwrap();
        let (x, y) = (plain.path.x_mm(), plain.path.y_mm());
        let ny = (1..x.len())
            .filter(|&k| (y[k] - y[k - 1]).abs() > 0.5)
            .count();
        let c = pitch_coefficient_x(&plain.path, 1.0);
        assert!((c - ny as f64).abs() < 1e-9 * ny as f64, "{c} vs {ny}");
        assert!(ny as f64 > 0.4 * (x.len() - 1) as f64);
        // Jittered nodes: a y step's expected coefficient is the mean over its four uniformly
        // jittered end coordinates (midpoint quadrature, 12^4 nodes) of its integral; the
        // nodes' own phases average sinc(pi J) (0 at J = 1) but the points between two nodes do
        // not, so a coherent part of that size remains (x steps add well under 0.02 each).
        for jit in [0.5, 1.0] {
            let q = 12;
            let u = |i: usize| jit * ((i as f64 + 0.5) / q as f64 - 0.5);
            let (mut re, mut im) = (0.0, 0.0);
            for (ia, ib, ic, id) in
                (0..q * q * q * q).map(|k| (k % q, k / q % q, k / (q * q) % q, k / (q * q * q)))
            {
                let (r, i) = segment_coefficient([u(ia), u(ic)], [u(ib), 1.0 + u(id)], 1.0);
                re += r;
                im += i;
            }
            let expect = re.hypot(im) / (q * q * q * q) as f64;
            let j = random_unicursal(
                &reg,
                &RandomPathSettings {
                    jitter: jit,
                    ..RandomPathSettings::default()
                },
            )
            .unwrap();
            let cj = pitch_coefficient_x(&j.path, 1.0) / ny as f64;
            assert!(
                expect < 0.8 && (cj - expect).abs() < 0.08,
                "J {jit}: {cj} vs {expect}"
            );
        }
    }
}
