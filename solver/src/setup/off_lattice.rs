//! When a solve uses an off-lattice matrix-free operator: map points on a regular lattice, dwell
//! points off it, a plane TIF and the first-order solver.
//!
//! - The operator the settings ask for (`stencil`, `nufft`, `fft-spread`), or an error naming
//!   why it cannot serve.
//! - With `auto`, the cheapest by the cost model below of those that reproduce the exact `R`:
//!   the phase-stencil operator ([`StencilOperator`], exact) where the dwell points take few
//!   distinct positions within a map cell (at most one per [`MIN_DWELL_POINTS_PER_STENCIL`]
//!   dwell points: a raster whose pitch is a rational multiple of the map's), the NUFFT
//!   operator ([`NufftOperator`]) where its estimated relative operator error is within
//!   [`DEFAULT_NUFFT_TOLERANCE`] at some refinement, and the spreading operator
//!   ([`SpreadOperator`]) where its estimated error is within that same tolerance (dwell points
//!   on an oversampled lattice, a rational pitch, spread exactly); each only where it is
//!   predicted cheaper than the assembled `R`.
//! - With `auto` and none of those, the spreading operator at `spread_tolerance` (approximate,
//!   the residual reported the exact `R`'s) where it is predicted cheaper than the assembled `R`.
//! - Where still none serves (a spiral or a random path under the swept model, whose stretches
//!   turn, or a TIF cut at a radius, whose jump no spreading resolves), the direction-expansion
//!   operator ([`ExpansionOperator`], [`Setup::expansion_plan`]): its error within
//!   `spread_tolerance` by construction, taken where predicted cheaper than the assembled `R`.
//!
//! Cost model (per `R^T R t`, the first-order solver's product): the sparse operator makes two
//! passes over the non-zeros, `2 nnz` multiply-adds at about [`SPARSE_NS_PER_NNZ`] (or one over
//! its Gram matrix where that is smaller, for the stencil's and the NUFFT operator's comparisons); the stencil
//! operator scatters and gathers every stencil entry, `2 n pi r^2 / h^2` at about
//! [`STENCIL_NS_PER_ENTRY`], and clears and weights its image of the lattice, two passes over its
//! cells at about [`IMAGE_NS_PER_CELL`]; the NUFFT operator spreads and gathers `w^2` weights a
//! dwell point at about [`NUFFT_NS_PER_WEIGHT`] and transforms its padded fine lattice like the
//! spreading operator; the spreading operator transforms the padded fine lattice of `F`
//! cells forth and back, about `F log2 F` times [`SPREAD_NS_PER_CELL_LOG`]. Assembling `R` costs
//! a TIF evaluation per non-zero on top, which the comparison leaves out (in the matrix-free
//! operators' favour).

use super::{At, Setup, SetupInput, SetupResult};
use crate::dwell::first_order::POWER_STEPS;
use crate::dwell::{policy, OperatorChoice, SolverChoice, SolverKind};
use crate::error::{twelve_figures, Error};
use crate::influence::operator::fft::FftOperator;
use crate::influence::operator::lattice::lattice_index;
use crate::influence::operator::nufft::{EsKernel, DEFAULT_NUFFT_TOLERANCE, UPSAMPLING};
use crate::influence::operator::spread::MAX_OVERSAMPLING;
use crate::influence::{
    ColumnShape, ExpansionOperator, InfluenceMatrix, NufftOperator, SpreadOperator, StencilOperator,
};
use crate::map::{BoundingBox, HeightMap};
use crate::observer::Observer;
use crate::tif::InfluenceFunction;

/// Sparse `R^T R t`: nanoseconds per stored non-zero (two passes, 2 cores).
pub const SPARSE_NS_PER_NNZ: f64 = 1.0;
/// Stencil `R^T R t`: nanoseconds per stencil entry and dwell point (two passes, 2 cores).
pub const STENCIL_NS_PER_ENTRY: f64 = 0.35;
/// Stencil `R^T R t`: nanoseconds per image cell (clearing and weighting the image, 2 cores).
pub const IMAGE_NS_PER_CELL: f64 = 0.5;
/// Spreading operator `R^T R t`: nanoseconds per `F log2 F` of the fine lattice (2 cores).
pub const SPREAD_NS_PER_CELL_LOG: f64 = 0.5;
/// NUFFT operator `R^T R t`: nanoseconds per spreading weight (one of `w^2` per dwell point,
/// spread and gathered: two passes, 2 cores).
pub const NUFFT_NS_PER_WEIGHT: f64 = 0.5;
/// `auto` takes the stencil operator only when each stencil serves this many dwell points on
/// average (the tables stay small next to `R`).
pub const MIN_DWELL_POINTS_PER_STENCIL: usize = 16;
/// The map must fill at least this share of its lattice's bounding box.
const MIN_LATTICE_FILL: f64 = 0.25;

/// The map lattice an off-lattice operator would work on, and the estimate of `R`'s size.
struct OffLattice {
    pitch_mm: f64,
    bbox: BoundingBox,
    /// Estimated non-zeros of `R`: the map points inside one TIF disc (at most all of them),
    /// times the dwell points.
    nnz: f64,
}

/// An off-lattice operator a set-up takes (see the module documentation).
pub(super) enum OffLatticeOperator {
    /// The phase-stencil operator.
    Stencil(StencilOperator),
    /// The NUFFT operator.
    Nufft(NufftOperator),
    /// The spreading operator.
    Spread(SpreadOperator),
}

/// An operator one of the plans built: its predicted nanoseconds per normal product (0 when the
/// settings asked for it) and, under `auto`, the note saying why it would be taken.
pub(super) struct Planned<T> {
    op: T,
    ns: f64,
    note: Option<String>,
}

impl<T> Planned<T> {
    fn forced(op: T) -> Self {
        Self {
            op,
            ns: 0.0,
            note: None,
        }
    }
}

/// Why an off-lattice operator does not serve a set-up.
enum NotServed {
    /// The inputs rule it out (an error when the operator was asked for).
    Cannot(String),
    /// `auto` prefers another operator.
    Declined,
}

impl Setup {
    /// Dwell points whose tool reach (the TIF's support radius) meets the bounding box of
    /// `rows`: the columns of `R` that can hold non-zeros, counted by the cost models (points
    /// that reach nothing add no work to `R`).
    pub(super) fn dwell_points_in_reach(&self, rows: &HeightMap) -> usize {
        let Some(b) = rows.bounding_box_mm() else {
            return 0;
        };
        let b = b.expanded(self.tif.support_radius_mm());
        self.path
            .x_mm()
            .iter()
            .zip(self.path.y_mm())
            .filter(|(&x, &y)| {
                x >= b.x_min_mm && x <= b.x_max_mm && y >= b.y_min_mm && y <= b.y_max_mm
            })
            .count()
    }

    /// Whether every dwell point lies on the map lattice of pitch `pitch_mm` through the lowest
    /// corner of `bbox` (the FFT operator's exact case).
    pub(super) fn dwell_on_map_lattice(&self, bbox: &BoundingBox, pitch_mm: f64) -> bool {
        let on = |v: f64, o: f64| lattice_index(v, o, pitch_mm).is_some();
        self.path
            .x_mm()
            .iter()
            .zip(self.path.y_mm())
            .all(|(&x, &y)| on(x, bbox.x_min_mm) && on(y, bbox.y_min_mm))
    }

    /// The checks both off-lattice operators share: nothing needs `R`, the map fills a regular
    /// lattice, and (unless `forced`) the first-order solver would run and the dwell points are
    /// off the lattice.
    fn off_lattice_case(&self, rows: &HeightMap, forced: bool) -> Result<OffLattice, NotServed> {
        self.matrix_free_case(rows, forced, false)
    }

    /// [`Setup::off_lattice_case`], with dwell points on the map lattice served too where
    /// `on_lattice` (the expansion operator: a random path on the lattice whose swept stretches
    /// turn, which the FFT operator's shared kernel does not serve).
    fn matrix_free_case(
        &self,
        rows: &HeightMap,
        forced: bool,
        on_lattice: bool,
    ) -> Result<OffLattice, NotServed> {
        if let Some(why) = self.fft_blocker() {
            return Err(NotServed::Cannot(format!("with {why}")));
        }
        let Some(pitch_mm) = FftOperator::lattice_pitch_mm(rows.x_mm(), rows.y_mm()) else {
            return Err(NotServed::Cannot(
                "the map points are not on a regular lattice".into(),
            ));
        };
        let Some(bbox) = rows.bounding_box_mm() else {
            return Err(NotServed::Cannot("the map is empty".into()));
        };
        let cells = ((bbox.x_max_mm - bbox.x_min_mm) / pitch_mm + 1.0)
            * ((bbox.y_max_mm - bbox.y_min_mm) / pitch_mm + 1.0);
        if (rows.len() as f64) < MIN_LATTICE_FILL * cells {
            return Err(NotServed::Cannot(format!(
                "the map fills less than {MIN_LATTICE_FILL} of its {} mm lattice",
                twelve_figures(pitch_mm)
            )));
        }
        let r = self.tif.support_radius_mm();
        let per_column =
            (std::f64::consts::PI * r * r / (pitch_mm * pitch_mm)).min(rows.len() as f64);
        let nnz = per_column * self.dwell_points_in_reach(rows) as f64;
        if !forced {
            // Only where the first-order solver would run anyway: below the policy's crossover
            // the QP on the assembled `R` is the faster, certified route.
            let first_order = match self.settings.solver {
                SolverChoice::FirstOrder => true,
                SolverChoice::Qp => false,
                SolverChoice::Auto => {
                    policy::choose(&policy::PolicyInputs {
                        nnz,
                        fft_cells: None,
                        needs_qp: false,
                        solver: None,
                    })
                    .solver
                        == SolverKind::FirstOrder
                }
            };
            if !first_order || (!on_lattice && self.dwell_on_map_lattice(&bbox, pitch_mm)) {
                return Err(NotServed::Declined);
            }
        }
        Ok(OffLattice {
            pitch_mm,
            bbox,
            nnz,
        })
    }

    /// The off-lattice operator over the problem rows `rows` (module documentation), `None` to
    /// assemble `R`: each plan in turn, a later one taken under `auto` only when predicted
    /// cheaper than the one before; the note of the one taken goes to `warnings`.
    pub(super) fn off_lattice_operator(
        &self,
        rows: &HeightMap,
        warnings: &mut Vec<String>,
    ) -> SetupResult<Option<OffLatticeOperator>> {
        let mut taken: Option<(OffLatticeOperator, f64, Option<String>)> = None;
        let cap = |t: &Option<(OffLatticeOperator, f64, Option<String>)>| {
            t.as_ref().map_or(f64::INFINITY, |t| t.1)
        };
        if let Some(p) = self.stencil_plan(rows, warnings)? {
            taken = Some((OffLatticeOperator::Stencil(p.op), p.ns, p.note));
        }
        if let Some(p) = self.nufft_plan(rows, warnings, cap(&taken))? {
            taken = Some((OffLatticeOperator::Nufft(p.op), p.ns, p.note));
        }
        if let Some(p) = self.spread_plan(rows, warnings, cap(&taken))? {
            taken = Some((OffLatticeOperator::Spread(p.op), p.ns, p.note));
        }
        Ok(taken.map(|(op, _, note)| {
            warnings.extend(note.map(super::note));
            op
        }))
    }

    /// The phase-stencil operator over the problem rows `rows` when it applies (see the module
    /// documentation); `None` otherwise. With `operator = "stencil"` inputs it cannot serve are
    /// an error naming why. Notes on the choice go to `warnings`.
    pub(super) fn stencil_plan(
        &self,
        rows: &HeightMap,
        warnings: &mut Vec<String>,
    ) -> SetupResult<Option<Planned<StencilOperator>>> {
        let forced = self.settings.operator == OperatorChoice::Stencil;
        if !forced && self.settings.operator != OperatorChoice::Auto {
            return Ok(None);
        }
        let case = match self.off_lattice_case(rows, forced) {
            Ok(case) => case,
            Err(not) => return refusal(forced, "stencil", not),
        };
        let (mx, my, dx, dy) = (rows.x_mm(), rows.y_mm(), self.path.x_mm(), self.path.y_mm());
        if !forced {
            let n = self.path.len();
            let Some(classes) = StencilOperator::phase_classes(
                mx,
                my,
                dx,
                dy,
                case.pitch_mm,
                n / MIN_DWELL_POINTS_PER_STENCIL,
            ) else {
                return Ok(None);
            };
            let r = self.tif.support_radius_mm();
            let entries = std::f64::consts::PI * r * r / (case.pitch_mm * case.pitch_mm);
            // The image spans map and dwell points with a stencil's reach around the dwell
            // points; every product clears it and weights it once.
            let extent = |v: &[f64]| {
                v.iter()
                    .fold((f64::INFINITY, f64::NEG_INFINITY), |(a, b), &x| {
                        (a.min(x), b.max(x))
                    })
            };
            let image_side = |(map_lo, map_hi): (f64, f64), (d_lo, d_hi): (f64, f64)| {
                ((map_hi.max(d_hi + r) - map_lo.min(d_lo - r)) / case.pitch_mm).max(0.0) + 1.0
            };
            let image_cells = image_side((case.bbox.x_min_mm, case.bbox.x_max_mm), extent(dx))
                * image_side((case.bbox.y_min_mm, case.bbox.y_max_mm), extent(dy));
            let stencil_ns = 2.0 * STENCIL_NS_PER_ENTRY * entries * n as f64
                + 2.0 * IMAGE_NS_PER_CELL * image_cells;
            let sparse_ns = self.sparse_normal_ns(rows, &case);
            if stencil_ns >= sparse_ns {
                return Ok(None);
            }
            let note = format!(
                "operator auto: dwell points off the map lattice, at {classes} distinct positions \
                 within a {:.4} mm cell; products use one tabulated stencil per position (exact), \
                 predicted {:.1}x cheaper than R's {:.2e} non-zeros (operator = \"sparse\" \
                 assembles R)",
                case.pitch_mm,
                sparse_ns / stencil_ns,
                case.nnz
            );
            return Ok(
                match StencilOperator::new(mx, my, dx, dy, case.pitch_mm, self.lattice_kernel()) {
                    Ok(op) => Some(Planned {
                        op,
                        ns: stencil_ns,
                        note: Some(note),
                    }),
                    Err(e) => {
                        warnings.push(format!(
                            "operator auto: the stencil operator does not apply ({e})"
                        ));
                        None
                    }
                },
            );
        }
        match StencilOperator::new(mx, my, dx, dy, case.pitch_mm, self.lattice_kernel()) {
            Ok(op) => Ok(Some(Planned::forced(op))),
            Err(e) if forced => Err(e).at(SetupInput::Map),
            Err(e) => {
                warnings.push(format!(
                    "operator auto: the stencil operator does not apply ({e}); assembling R"
                ));
                Ok(None)
            }
        }
    }

    /// Predicted nanoseconds of one `R^T R t` with the assembled `R` (see the module
    /// documentation): two passes over `R`, or one over its Gram matrix where forming it costs
    /// no more than the solver's first products.
    fn sparse_normal_ns(&self, rows: &HeightMap, case: &OffLattice) -> f64 {
        let (dx, dy) = (self.path.x_mm(), self.path.y_mm());
        let n = self.path.len();
        let r = self.tif.support_radius_mm();
        // The assembled `R` serves normal products through `R` (two passes) or, where its
        // formation (`k^2` multiply-adds per map point, `k` the dwell points in its reach)
        // costs at most the products the solver declares, through its Gram matrix (one pass
        // over `G`: each dwell point against those within `2 r`).
        // Dwell points per mm^2 where there are any: over the squares of side `r / 2` they
        // occupy (a few stray points far out do not thin the estimate, nor do the half-empty
        // squares along the path's outline, which at side `2 r` halved it on a 1 mm raster and
        // had the Gram matrix predicted where `GramMatrix::worthwhile` declines it).
        let square = 0.5 * r;
        let occupied: std::collections::HashSet<(i64, i64)> = dx
            .iter()
            .zip(dy)
            .map(|(&x, &y)| ((x / square).floor() as i64, (y / square).floor() as i64))
            .collect();
        let per_mm2 = n as f64 / (occupied.len().max(1) as f64 * square * square);
        let in_reach = (std::f64::consts::PI * r * r * per_mm2).min(n as f64);
        let formation = rows.len() as f64 * in_reach * in_reach;
        let gram_nnz = (4.0 * std::f64::consts::PI * r * r * per_mm2).min(n as f64) * n as f64;
        let through_r = 2.0 * case.nnz;
        SPARSE_NS_PER_NNZ
            * if formation <= through_r * POWER_STEPS as f64 {
                through_r.min(gram_nnz)
            } else {
                through_r
            }
    }

    /// The NUFFT operator over the problem rows `rows` when it applies (see the module
    /// documentation); `None` otherwise. With `operator = "nufft"` inputs it cannot serve are an
    /// error naming why; a TIF no refinement brings within the tolerance is then used at its
    /// best refinement with a warning. Notes on the choice go to `warnings`.
    pub(super) fn nufft_plan(
        &self,
        rows: &HeightMap,
        warnings: &mut Vec<String>,
        cap_ns: f64,
    ) -> SetupResult<Option<Planned<NufftOperator>>> {
        let forced = self.settings.operator == OperatorChoice::Nufft;
        if !forced && self.settings.operator != OperatorChoice::Auto {
            return Ok(None);
        }
        let case = match self.off_lattice_case(rows, forced) {
            Ok(case) => case,
            Err(not) => return refusal(forced, "nufft", not),
        };
        let (mx, my, dx, dy) = (rows.x_mm(), rows.y_mm(), self.path.x_mm(), self.path.y_mm());
        let pitch = case.pitch_mm;
        let tolerance = DEFAULT_NUFFT_TOLERANCE;
        let w = EsKernel::for_tolerance(tolerance, UPSAMPLING).width as f64;
        let r = self.lattice_kernel().support_radius_mm();
        let extent = |v: &[f64], lo: f64, hi: f64| {
            let (a, b) = v.iter().fold((lo, hi), |(a, b), &x| (a.min(x), b.max(x)));
            b - a
        };
        let (ex, ey) = (
            extent(dx, case.bbox.x_min_mm, case.bbox.x_max_mm),
            extent(dy, case.bbox.y_min_mm, case.bbox.y_max_mm),
        );
        let n = self.path.len() as f64;
        // Spread and gather (`w^2` weights a point each) and the inner FFT operator's transforms
        // over the fine lattice padded by the deconvolved kernel's reach (TIF + `w` cells).
        let nufft_ns = |s: usize| {
            let fine = pitch / s as f64;
            let pad = 2.0 * (r / fine + 2.0 * w);
            let cells = (ex / fine + pad) * (ey / fine + pad);
            2.0 * NUFFT_NS_PER_WEIGHT * n * w * w
                + SPREAD_NS_PER_CELL_LOG * cells * cells.max(2.0).log2()
        };
        let sparse_ns = self.sparse_normal_ns(rows, &case);
        let beat_ns = sparse_ns.min(cap_ns);
        if !forced && nufft_ns(1) >= beat_ns {
            return Ok(None);
        }
        let chosen = match NufftOperator::refinement_for(
            mx,
            my,
            dx,
            dy,
            pitch,
            self.lattice_kernel(),
            tolerance,
        ) {
            Ok(c) => c,
            Err(e) => return refusal(forced, "nufft", NotServed::Cannot(e.to_string())),
        };
        let (s, error) = match chosen {
            Ok((s, error)) if forced => {
                warnings.push(format!(
                    "operator nufft: refinement {s} ({:.4} mm lattice), estimated operator error \
                     {error:.1e} <= {tolerance:.0e}",
                    pitch / s as f64
                ));
                (s, error)
            }
            Ok(c) => c,
            Err((s, error)) if forced => {
                warnings.push(format!(
                    "operator nufft: the TIF has content beyond the lattices' band: the smallest \
                     estimated operator error, {error:.1e} (refinement {s}), is above the \
                     design tolerance {tolerance:.0e}; the residual reported is the exact R's"
                ));
                (s, error)
            }
            Err(_) => return Ok(None),
        };
        let note = if forced {
            None
        } else {
            if nufft_ns(s) >= beat_ns {
                return Ok(None);
            }
            Some(format!(
                "operator auto: dwell points off the map lattice; products spread them by a \
                 smooth kernel onto a {:.4} mm lattice (NUFFT, estimated operator error \
                 {error:.1e} <= {tolerance:.0e}), predicted {:.1}x cheaper per product than R \
                 (operator = \"sparse\" assembles R)",
                pitch / s as f64,
                sparse_ns / nufft_ns(s)
            ))
        };
        match NufftOperator::new(mx, my, dx, dy, pitch, s, tolerance, self.lattice_kernel()) {
            Ok(op) => Ok(Some(Planned {
                op,
                ns: nufft_ns(s),
                note,
            })),
            Err(e) if forced => Err(e).at(SetupInput::Map),
            Err(e) => {
                warnings.push(format!(
                    "operator auto: the NUFFT operator does not apply ({e}); assembling R"
                ));
                Ok(None)
            }
        }
    }

    /// The spreading operator over the problem rows `rows` when it applies (see the module
    /// documentation); `None` to assemble `R`. With `operator = "fft-spread"` inputs it cannot
    /// serve are an error naming why. Notes on the choice go to `warnings`.
    pub(super) fn spread_plan(
        &self,
        rows: &HeightMap,
        warnings: &mut Vec<String>,
        cap_ns: f64,
    ) -> SetupResult<Option<Planned<SpreadOperator>>> {
        let forced = self.settings.operator == OperatorChoice::FftSpread;
        if !forced && self.settings.operator != OperatorChoice::Auto {
            return Ok(None);
        }
        let case = match self.off_lattice_case(rows, forced) {
            Ok(case) => case,
            Err(not) => return refusal(forced, "fft-spread", not),
        };
        let OffLattice {
            pitch_mm: pitch,
            bbox,
            nnz,
        } = case;
        let (mx, my, dx, dy) = (rows.x_mm(), rows.y_mm(), self.path.x_mm(), self.path.y_mm());
        let r = self.tif.support_radius_mm();
        let sparse_ns = (2.0 * SPARSE_NS_PER_NNZ * nnz).min(cap_ns);
        let spread_ns = |s: usize| {
            let fine = pitch / s as f64;
            let pad = 2.0 * r / fine;
            let lattice = ((bbox.x_max_mm - bbox.x_min_mm) / fine + pad)
                * ((bbox.y_max_mm - bbox.y_min_mm) / fine + pad);
            SPREAD_NS_PER_CELL_LOG * lattice * lattice.max(2.0).log2()
        };
        if !forced && spread_ns(1) >= sparse_ns {
            return Ok(None);
        }
        // Against an operator that reproduces `R`, only a spreading that does as well.
        let tolerance = if cap_ns.is_finite() && !forced {
            self.settings.spread_tolerance.min(DEFAULT_NUFFT_TOLERANCE)
        } else {
            self.settings.spread_tolerance
        };
        let chosen = match SpreadOperator::oversampling_for(
            mx,
            my,
            dx,
            dy,
            pitch,
            self.lattice_kernel(),
            tolerance,
        ) {
            Ok(c) => c,
            Err(e) => return refusal(forced, "fft-spread", NotServed::Cannot(e.to_string())),
        };
        let Some((s, error)) = chosen else {
            if !forced && cap_ns.is_finite() {
                return Ok(None);
            }
            return refusal(
                forced,
                "fft-spread",
                NotServed::Cannot(format!(
                    "no oversampling up to {MAX_OVERSAMPLING} brings the estimated operator error \
                     within spread_tolerance = {tolerance}"
                )),
            );
        };
        let note = if forced {
            None
        } else {
            if spread_ns(s) >= sparse_ns {
                return Ok(None);
            }
            Some(format!(
                "operator auto: dwell points off the map lattice; products spread them onto a \
                 {:.4} mm lattice (oversampling {s}, estimated operator error {error:.1e} <= \
                 {tolerance:.0e}) and use the FFT, about {:.0}x cheaper per product than R's \
                 {nnz:.2e} non-zeros (operator = \"sparse\" assembles R)",
                pitch / s as f64,
                sparse_ns / spread_ns(s)
            ))
        };
        match SpreadOperator::new(mx, my, dx, dy, pitch, s, self.lattice_kernel()) {
            Ok(op) => Ok(Some(Planned {
                op,
                ns: spread_ns(s),
                note,
            })),
            Err(e) if forced => Err(e).at(SetupInput::Map),
            Err(e) => {
                warnings.push(format!(
                    "operator auto: the spreading operator does not apply ({e}); assembling R"
                ));
                Ok(None)
            }
        }
    }
}

/// What [`Setup::expansion_plan`] found: the expansion operator, or the exact `R` it assembled
/// (to solve on where the operator is not predicted faster).
pub(super) enum ExpansionPlan {
    /// The expansion operator, taken.
    Taken(ExpansionOperator),
    /// The assembled `R`, taken.
    Assembled(InfluenceMatrix),
}

/// Spreading products per expansion product (the TIF and its three direction terms).
pub const EXPANSION_TERMS: f64 = 4.0;
/// Expansion operator `R^T R t`: nanoseconds per entry of its exact correction (two passes, 2
/// cores): about twice the assembled `R`'s per non-zero, measured on the 60 mm round part of
/// `scripts/round_part.py` (the correction's rows are scattered over every dwell point).
pub const CORRECTION_NS_PER_ENTRY: f64 = 2.0 * SPARSE_NS_PER_NNZ;

impl Setup {
    /// The direction-expansion operator ([`ExpansionOperator`]) over the problem rows `rows`
    /// where no other matrix-free operator serves (a spiral or a random path under the swept
    /// model, a TIF cut at a radius): `None` when it does not apply (assemble `R` as usual).
    /// Under `auto` it is taken only where predicted cheaper per normal product than the
    /// assembled `R` (four spreading products on the map lattice and two passes over the
    /// correction, against two passes over `R`, [`Setup::sparse_normal_ns`]); its error is
    /// within `spread_tolerance` by construction (summed over every entry). The build assembles
    /// `R`, which is returned to solve on where the operator is declined.
    pub(super) fn expansion_plan(
        &self,
        rows: &HeightMap,
        warnings: &mut Vec<String>,
        observer: &dyn Observer,
    ) -> SetupResult<Option<ExpansionPlan>> {
        let forced = self.settings.operator == OperatorChoice::Expansion;
        if !forced && self.settings.operator != OperatorChoice::Auto {
            return Ok(None);
        }
        let case = match self.matrix_free_case(rows, forced, true) {
            Ok(case) => case,
            Err(not) => return refusal(forced, "expansion", not),
        };
        let pitch = case.pitch_mm;
        let bbox = case.bbox;
        let r = self.tif.support_radius_mm();
        let fine = pitch;
        let pad = 2.0 * r / fine;
        let lattice = ((bbox.x_max_mm - bbox.x_min_mm) / fine + pad)
            * ((bbox.y_max_mm - bbox.y_min_mm) / fine + pad);
        let spread_ns =
            EXPANSION_TERMS * SPREAD_NS_PER_CELL_LOG * lattice * lattice.max(2.0).log2();
        let sparse_ns = self.sparse_normal_ns(rows, &case);
        if !forced && spread_ns >= sparse_ns {
            return Ok(None);
        }
        let exact = self.assemble(rows, observer)?;
        let shapes = ColumnShape::of(
            self.path.x_mm(),
            self.path.y_mm(),
            self.swept.as_ref().map(|s| &s.0),
        );
        let tolerance = self.settings.spread_tolerance;
        let op = match ExpansionOperator::new(
            rows.x_mm(),
            rows.y_mm(),
            &shapes,
            &exact,
            pitch,
            1,
            &self.tif,
            tolerance,
        ) {
            Ok(op) => op,
            Err(e) if forced => return Err(e).at(SetupInput::Map),
            Err(e) => {
                warnings.push(format!(
                    "operator auto: the expansion operator does not apply ({e}); assembling R"
                ));
                return Ok(Some(ExpansionPlan::Assembled(exact)));
            }
        };
        let ns = spread_ns + 2.0 * CORRECTION_NS_PER_ENTRY * op.correction_nnz() as f64;
        let what = format!(
            "each column the TIF and its second-order expansion along its stretch ({:.3} mm \
             reference), spread onto the {:.4} mm map lattice, with {:.1}% of R's entries exact \
             (a cut TIF's edge, odd stretches); operator error {:.1e} <= {tolerance:.0e} over \
             every entry",
            op.reference_mm(),
            pitch,
            100.0 * op.correction_share(),
            op.estimated_error()
        );
        if forced {
            warnings.push(super::note(format!("operator expansion: {what}")));
            return Ok(Some(ExpansionPlan::Taken(op)));
        }
        if ns >= sparse_ns {
            warnings.push(super::note(format!(
                "operator auto: the expansion operator ({what}) is predicted no cheaper than \
                 R's {:.2e} non-zeros; assembling R",
                case.nnz
            )));
            return Ok(Some(ExpansionPlan::Assembled(exact)));
        }
        warnings.push(super::note(format!(
            "operator auto: dwell points off the map lattice with stretches of their own; {what}, \
             predicted {:.1}x cheaper per product than R (operator = \"sparse\" assembles R)",
            sparse_ns / ns
        )));
        Ok(Some(ExpansionPlan::Taken(op)))
    }
}

/// `None` (the assembled `R`) when `auto` finds the operator `name` does not serve, an error
/// naming why when the settings asked for it.
fn refusal<T>(forced: bool, name: &str, not: NotServed) -> SetupResult<Option<T>> {
    match not {
        NotServed::Cannot(why) if forced => Err(Error::invalid(
            "operator",
            format!("operator = \"{name}\" cannot be used: {why}"),
        ))
        .at(SetupInput::Job),
        _ => Ok(None),
    }
}
