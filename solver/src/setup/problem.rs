//! [`Setup::problem`]: the rows (map and edge model), how `R` is held (assembled, FFT, off-lattice
//! operators, or the robust plan's stacked scenarios) and the [`Problem`] built on them.

use super::off_lattice::{ExpansionPlan, OffLatticeOperator};
use super::*;
use crate::influence::model::curvature::hertz_tifs_on_surface;
use crate::influence::model::piece::piece_rate;
use crate::influence::model::surface::{assemble_on_surface_swept_with, assemble_on_surface_with};
use crate::influence::operator::stacked::ScenarioOperators;
use crate::influence::operator::InfluenceOperator;
use crate::influence::operator::OperatorKind;
use crate::influence::swept_correction::SweptCorrected;
use crate::influence::{NufftOperator, SpreadOperator, StackedRows, StencilOperator, SweptTif};
use crate::tif::{Perturbation, PerturbedTif};
use std::sync::Arc;

/// Under `operator = "auto"`, the largest share of dwell points whose swept columns a lattice
/// operator corrects one by one (a raster's row ends are a few per cent; a spiral's points all
/// differ).
pub const MAX_CORRECTED_SHARE: f64 = 0.2;

/// The FFT operator is used only when the map's bounding box holds at most this many lattice cells
/// per map point (a round aperture fills 79% of its square, i.e. 1.27 cells per point).
pub(super) const MAX_LATTICE_CELLS_PER_MAP_POINT: f64 = 4.0;

/// `auto` takes the FFT operator only where its padded lattice (map and dwell points, the TIF's
/// reach around them) holds at most this many cells per map or dwell point: a few dwell points
/// far from the others would otherwise make a mostly empty lattice of hundreds of MB (a padded
/// raster over a strip holds about 3).
pub(super) const MAX_FFT_CELLS_PER_POINT: f64 = 16.0;

/// Cells of the FFT operator's lattice (pitch `pitch` mm) for `map` and `path`, padded by the
/// TIF's support radius `radius` mm on every side: the cost model's size.
pub(super) fn fft_lattice_cells(map: &HeightMap, path: &DwellPath, radius: f64, pitch: f64) -> f64 {
    let span = |v: &mut dyn Iterator<Item = &f64>| {
        let (lo, hi) = v.fold((f64::INFINITY, f64::NEG_INFINITY), |(a, b), &x| {
            (a.min(x), b.max(x))
        });
        ((hi - lo).max(0.0) + 2.0 * radius) / pitch + 1.0
    };
    span(&mut map.x_mm().iter().chain(path.x_mm()))
        * span(&mut map.y_mm().iter().chain(path.y_mm()))
}

/// How a lattice operator was built: its kind and the parameters chosen for the nominal kernel,
/// so that a robust scenario builds the same operator with its own kernel.
#[derive(Clone, Copy, Debug, PartialEq)]
pub(super) enum LatticeBuild {
    /// The FFT operator (dwell points on the map's lattice or a sub-lattice of it).
    Fft,
    /// The phase-stencil operator.
    Stencil,
    /// The NUFFT operator at `refinement`, its spreading kernel designed for `tolerance`.
    Nufft {
        /// Fine lattice pitch is the map's over this.
        refinement: usize,
        /// Design tolerance of the exponential-of-semicircle kernel.
        tolerance: f64,
    },
    /// The bilinear spreading operator at `oversampling`.
    Spread {
        /// Fine lattice pitch is the map's over this.
        oversampling: usize,
    },
}

impl Setup {
    /// The problem's rows: the measured map, then the edge extension into the dwell area.
    pub(super) fn rows(&self) -> SetupResult<(HeightMap, usize)> {
        let map = &self.map;
        let extension = edge::extend(
            &self.edge,
            map.x_mm(),
            map.y_mm(),
            map.z_nm(),
            self.path.x_mm(),
            self.path.y_mm(),
            self.tif.nominal_radius_mm(),
            self.tif.support_radius_mm(),
        )
        .at(SetupInput::Map)?;
        let edge_points = extension.len();
        if extension.is_empty() {
            return Ok((map.clone(), 0));
        }
        let cat = |a: &[f64], b: &[f64]| [a, b].concat();
        let rows = HeightMap::new(
            cat(map.x_mm(), &extension.x_mm),
            cat(map.y_mm(), &extension.y_mm),
            cat(map.z_nm(), &extension.z_nm),
        )
        .at(SetupInput::Map)?;
        Ok((rows, edge_points))
    }

    /// The shift-invariant kernel of the lattice operators: the TIF swept along the stretch most
    /// dwell points share (swept model), or the TIF itself (point model).
    pub(crate) fn lattice_kernel(&self) -> &dyn InfluenceFunction {
        match &self.swept {
            Some((_, kernel)) => kernel,
            None => &self.tif,
        }
    }

    /// What keeps the FFT operator from serving this set-up, if anything.
    pub(super) fn fft_blocker(&self) -> Option<&'static str> {
        if self.surface.is_some() {
            Some("a [surface] file (the TIF acts in each point's tangent frame)")
        } else if self
            .accel
            .as_ref()
            .is_some_and(|a| a.method.needs_assembled_r())
        {
            Some("accel_method = \"scp-qp\" or \"squared-speed-then-scp-qp\" (the sequential QP needs R)")
        } else if self.settings.min_time {
            Some("the minimum-time mode (it runs the QP)")
        } else if self.settings.solver == SolverChoice::Qp {
            Some("solver = \"qp\" (the QP needs R)")
        } else {
            None
        }
    }

    /// How `R` is held for the problem rows `rows` (`operator` of the settings): `fft` with
    /// inputs it cannot serve is an error naming why; `auto` takes the FFT operator when the
    /// cost models of [`policy::choose`] predict it faster than the assembled `R`, the map fills
    /// its lattice and nothing blocks it (a warning says so), the assembled matrix otherwise.
    pub fn operator_plan(
        &self,
        rows: &HeightMap,
        warnings: &mut Vec<String>,
    ) -> SetupResult<OperatorPlan> {
        let choice = self.settings.operator;
        // The off-lattice operators are planned by `off_lattice_operator` where the lattice one
        // is not.
        if matches!(
            choice,
            OperatorChoice::Sparse
                | OperatorChoice::FftSpread
                | OperatorChoice::Stencil
                | OperatorChoice::Nufft
                | OperatorChoice::Expansion
        ) {
            return Ok(OperatorPlan::Assembled);
        }
        let blocker = self.fft_blocker();
        // The map must fill a fair share of its lattice (a gridded map, perhaps with a round
        // aperture), or the FFT buffers would dwarf the map.
        let pitch = FftOperator::lattice_pitch_mm(rows.x_mm(), rows.y_mm()).filter(|&p| {
            rows.bounding_box_mm().is_some_and(|b| {
                let cells =
                    ((b.x_max_mm - b.x_min_mm) / p + 1.0) * ((b.y_max_mm - b.y_min_mm) / p + 1.0);
                cells <= MAX_LATTICE_CELLS_PER_MAP_POINT * rows.len() as f64
            })
        });
        match (choice, blocker, pitch) {
            (OperatorChoice::Fft, Some(why), _) => Err(Error::invalid(
                "operator",
                format!("operator = \"fft\" cannot be used with {why}"),
            ))
            .at(SetupInput::Job),
            (OperatorChoice::Fft, None, None) => Err(Error::invalid(
                "operator",
                "operator = \"fft\" needs map points on a regular lattice that they fill at \
                 least a quarter of",
            ))
            .at(SetupInput::Job),
            (OperatorChoice::Fft, None, Some(p)) => Ok(OperatorPlan::Fft { pitch_mm: p }),
            (_, Some(_), _) | (_, None, None) => Ok(OperatorPlan::Assembled),
            // Dwell points off the lattice are the off-lattice operators' case.
            (_, None, Some(p))
                if !rows
                    .bounding_box_mm()
                    .is_some_and(|b| self.dwell_on_map_lattice(&b, p)) =>
            {
                Ok(OperatorPlan::Assembled)
            }
            (_, None, Some(p)) => {
                // Map points inside one TIF disc, at most all of them, per dwell point.
                let r = self.tif.support_radius_mm();
                let per_column = (std::f64::consts::PI * r * r / (p * p)).min(rows.len() as f64);
                let estimate = per_column * self.dwell_points_in_reach(rows) as f64;
                let fft_cells = fft_lattice_cells(rows, &self.path, r, p);
                let points = (rows.len() + self.path.len()) as f64;
                if fft_cells > MAX_FFT_CELLS_PER_POINT * points {
                    warnings.push(format!(
                        "operator auto: the FFT lattice spanning the map and dwell points would \
                         hold {fft_cells:.3e} cells for {points:.0} points (dwell points far from \
                         the others?), mostly empty; assembling R (operator = \"fft\" forces it)"
                    ));
                    return Ok(OperatorPlan::Assembled);
                }
                let choice = policy::choose(&policy::PolicyInputs {
                    nnz: estimate,
                    fft_cells: Some(fft_cells),
                    needs_qp: false,
                    solver: match self.settings.solver {
                        SolverChoice::FirstOrder => Some(SolverKind::FirstOrder),
                        SolverChoice::Qp => Some(SolverKind::Qp),
                        SolverChoice::Auto => None,
                    },
                });
                if choice.operator == policy::OperatorKind::Fft {
                    warnings.push(super::note(format!(
                        "operator auto: about {estimate:.2e} non-zeros in R; the FFT operator is \
                         predicted faster ({:.2} s against {:.2} s first-order with R, {:.2} s QP), \
                         so products use it (operator = \"sparse\" assembles R)",
                        choice.first_order_fft_s, choice.first_order_sparse_s, choice.qp_s
                    )));
                    Ok(OperatorPlan::Fft { pitch_mm: p })
                } else {
                    Ok(OperatorPlan::Assembled)
                }
            }
        }
    }

    /// Assembles `R` over `rows`: in the plane, in each dwell point's tangent frame on the design
    /// surface, or with a curvature-dependent TIF per dwell point.
    pub(super) fn assemble(
        &self,
        rows: &HeightMap,
        observer: &dyn Observer,
    ) -> SetupResult<InfluenceMatrix> {
        self.assemble_scenario(rows, &Perturbation::NONE, observer)
    }

    /// [`Setup::assemble`] with the tool perturbed by `p`: its TIF wider and its rate higher, and
    /// the tool off by `p.offset_mm` in plan (in the plane the TIF's shift; on a curved part the
    /// dwell points moved, their frames and curvatures taken where the tool lands).
    pub(super) fn assemble_scenario(
        &self,
        rows: &HeightMap,
        p: &Perturbation,
        observer: &dyn Observer,
    ) -> SetupResult<InfluenceMatrix> {
        let (mx, my) = (rows.x_mm(), rows.y_mm());
        let stretches = self.swept.as_ref().map(|s| &s.0);
        let Some(surface) = &self.surface else {
            let tif = p.of(&self.tif);
            return match stretches {
                Some(st) => assemble_swept(mx, my, &self.path, st, &tif, observer),
                None => InfluenceMatrix::assemble(
                    mx,
                    my,
                    self.path.x_mm(),
                    self.path.y_mm(),
                    &tif,
                    observer,
                ),
            }
            .at(SetupInput::None);
        };
        let moved;
        let path = if p.offset_mm == (0.0, 0.0) {
            &self.path
        } else {
            let (ox, oy) = p.offset_mm;
            moved = DwellPath::new(
                self.path.x_mm().iter().map(|x| x + ox).collect(),
                self.path.y_mm().iter().map(|y| y + oy).collect(),
            )
            .at(SetupInput::Surface)?;
            &moved
        };
        let at_tool = Perturbation {
            offset_mm: (0.0, 0.0),
            ..*p
        };
        let (px, py) = (path.x_mm(), path.y_mm());
        let frame = self.tif_frame;
        match &self.tif_model {
            TifModel::ShiftInvariant => {
                let tif = at_tool.of(&self.tif);
                match stretches {
                    Some(st) => {
                        assemble_on_surface_swept(surface, mx, my, path, st, &tif, frame, observer)
                    }
                    None => assemble_on_surface(surface, mx, my, px, py, &tif, frame, observer),
                }
            }
            // Each dwell point's own Hertz TIF (unperturbed: exactly the curvature-dependent
            // assembly of `influence::model::curvature`).
            TifModel::CurvatureDependent(params) => {
                let tifs =
                    hertz_tifs_on_surface(surface, px, py, params).at(SetupInput::Surface)?;
                let radius = tifs
                    .iter()
                    .map(|t| at_tool.of(t).support_radius_mm())
                    .fold(0.0, f64::max);
                let piece = |j: usize, half: [f64; 2], u: f64, w: f64| {
                    tifs.get(j)
                        .map_or(0.0, |t| piece_rate(&at_tool.of(t), half, u, w))
                };
                match stretches {
                    Some(st) => assemble_on_surface_swept_with(
                        surface, mx, my, path, st, radius, piece, frame, observer,
                    ),
                    None => assemble_on_surface_with(
                        surface,
                        mx,
                        my,
                        px,
                        py,
                        radius,
                        |j, u, w| piece(j, [0.0, 0.0], u, w),
                        frame,
                        observer,
                    ),
                }
            }
        }
        .at(SetupInput::Surface)
    }

    /// Builds the problem: the edge extension, the operator (assembled or FFT) and the
    /// validated [`Problem`].
    pub fn problem(&self, observer: &dyn Observer) -> SetupResult<Built> {
        observer.setup_step(SetupStep::BuildProblem);
        if let Some(why) = plausible::tif_narrower_than_the_map_spacing(&self.map, &self.tif) {
            return Err(Error::invalid("TIF", why)).at(SetupInput::None);
        }
        let (rows, edge_points) = self.rows()?;
        let mut warnings = plausible::size_warnings(&self.map, &self.tif);
        if self.settings.robust {
            let (problem, weights) = self.robust_problem(&rows, &mut warnings, observer)?;
            let mut built = self.built(problem, edge_points, warnings)?;
            built.scenario_weights = Some(weights);
            return Ok(built);
        }
        let z_nm = rows.z_nm().to_vec();
        let (bounds, rho, lambda) = (self.bounds.clone(), self.rho, self.lambda);
        let lattice = self
            .lattice_operator(&rows, &mut warnings)?
            .map(|(op, _)| op);
        let lattice = match (lattice, &self.swept) {
            (Some(op), Some((_, kernel))) => {
                self.swept_corrected(op, &rows, &self.tif, kernel, &mut warnings, observer)?
            }
            (lattice, _) => lattice,
        };
        let problem = match lattice {
            Some(op) => Problem::from_boxed(op, z_nm, bounds, rho, lambda),
            None => match self.expansion_plan(&rows, &mut warnings, observer)? {
                Some(ExpansionPlan::Taken(op)) => Problem::new(op, z_nm, bounds, rho, lambda),
                Some(ExpansionPlan::Assembled(r)) => Problem::new(r, z_nm, bounds, rho, lambda),
                None => Problem::new(self.assemble(&rows, observer)?, z_nm, bounds, rho, lambda),
            },
        }
        .and_then(|p| {
            p.with_dwell_lattice(DwellLattice::detect(self.path.x_mm(), self.path.y_mm()))
        })
        .at(SetupInput::Job)?;
        self.built(problem, edge_points, warnings)
    }

    /// The matrix-free operator over the problem rows `rows` with the lattice kernel
    /// ([`Setup::lattice_kernel`]): the FFT operator where [`Setup::operator_plan`] takes it,
    /// else the off-lattice operator [`Setup::off_lattice_operator`] takes; `None` to assemble
    /// `R`, with how it was built. Notes on the choice go to `warnings`.
    fn lattice_operator(
        &self,
        rows: &HeightMap,
        warnings: &mut Vec<String>,
    ) -> SetupResult<Option<(Box<dyn InfluenceOperator>, LatticeBuild)>> {
        let fft = match self.operator_plan(rows, warnings)? {
            OperatorPlan::Assembled => None,
            OperatorPlan::Fft { pitch_mm } => match FftOperator::new(
                rows.x_mm(),
                rows.y_mm(),
                self.path.x_mm(),
                self.path.y_mm(),
                pitch_mm,
                self.lattice_kernel(),
            ) {
                Ok(op) => Some(op),
                Err(e) if self.settings.operator == OperatorChoice::Fft => {
                    return Err(e).at(SetupInput::Map);
                }
                Err(e) => {
                    warnings.push(format!(
                        "operator auto: the FFT operator does not apply ({e}); assembling R"
                    ));
                    None
                }
            },
        };
        Ok(match fft {
            Some(op) => Some((Box::new(op), LatticeBuild::Fft)),
            None => match self.off_lattice_operator(rows, warnings)? {
                Some(OffLatticeOperator::Stencil(op)) => {
                    Some((Box::new(op), LatticeBuild::Stencil))
                }
                Some(OffLatticeOperator::Nufft(op)) => {
                    let build = LatticeBuild::Nufft {
                        refinement: op.refinement(),
                        tolerance: op.tolerance(),
                    };
                    Some((Box::new(op), build))
                }
                Some(OffLatticeOperator::Spread(op)) => {
                    let build = LatticeBuild::Spread {
                        oversampling: op.oversampling(),
                    };
                    Some((Box::new(op), build))
                }
                None => None,
            },
        })
    }

    /// `problem` with its checks: refused when no dwell point reaches the map, warned when a
    /// large share reaches nothing.
    pub(super) fn built(
        &self,
        problem: Problem,
        edge_points: usize,
        mut warnings: Vec<String>,
    ) -> SetupResult<Built> {
        let empty = problem.empty_columns().len();
        if let Some(why) = plausible::no_dwell_point_reaches_the_map(empty, problem.n(), &self.tif)
        {
            return Err(Error::invalid("dwell path", why)).at(SetupInput::None);
        }
        warnings.extend(plausible::unreachable_share_warning(empty, problem.n()));
        let (warnings, notes) = super::split_notes(warnings);
        Ok(Built {
            problem,
            edge_points,
            warnings,
            notes,
            scenario_weights: None,
        })
    }

    /// A lattice operator `op` over the rows `rows` with the swept model's exact columns where
    /// a dwell point's stretch is not the shared kernel's
    /// ([`crate::influence::swept_correction`]); `op` itself under the point model or when
    /// every stretch is the kernel's. `None` (assemble `R`) under `operator = "auto"` when more
    /// than [`MAX_CORRECTED_SHARE`] of the dwell points need their own columns (a spiral, a
    /// random path: the shared kernel is not the path's, and the correction would cost more
    /// than the assembled `R`).
    /// `tif` is the TIF swept along each stretch and `kernel` the operator's shared kernel (the
    /// nominal ones, or a robust scenario's).
    fn swept_corrected<T: InfluenceFunction + ?Sized, K: InfluenceFunction + ?Sized>(
        &self,
        op: Box<dyn InfluenceOperator>,
        rows: &HeightMap,
        tif: &T,
        kernel: &K,
        warnings: &mut Vec<String>,
        observer: &dyn Observer,
    ) -> SetupResult<Option<Box<dyn InfluenceOperator>>> {
        let Some((stretches, _)) = &self.swept else {
            return Ok(Some(op));
        };
        let columns = stretches.outside_dominant();
        let share = columns.len() as f64 / self.path.len().max(1) as f64;
        if self.settings.operator == OperatorChoice::Auto && share > MAX_CORRECTED_SHARE {
            warnings.push(format!(
                "operator auto: {:.0}% of the dwell points' stretches differ from the lattice \
                 operator's shared swept kernel; the expansion operator where it pays, else \
                 assembling R",
                100.0 * share
            ));
            return Ok(None);
        }
        match SweptCorrected::new(
            op,
            rows.x_mm(),
            rows.y_mm(),
            &self.path,
            stretches,
            columns,
            tif,
            kernel,
            observer,
        )
        .at(SetupInput::None)?
        {
            Ok(corrected) => {
                warnings.push(super::note(format!(
                    "influence swept: {} dwell points whose stretch differs from the lattice \
                     operator's shared kernel (row ends, the path's ends) have their exact \
                     columns",
                    corrected.corrected_columns()
                )));
                Ok(Some(Box::new(corrected)))
            }
            Err(op) => Ok(Some(op)),
        }
    }

    /// The robust scenarios' matrix-free operators over the problem rows `rows`, the nominal
    /// first ([`Setup::robust_scenarios`]): where the nominal plan takes a lattice operator (FFT,
    /// stencil, NUFFT or spreading), the same operator with the nominal's parameters and each
    /// scenario's kernel (its TIF, [`PerturbedTif`], swept along the dominant stretch under the
    /// swept model), each with its exact swept columns where stretches differ. `None` to stack
    /// the assembled matrices (`operator = "sparse"`, or a nominal plan on `R`).
    fn robust_lattice_blocks(
        &self,
        rows: &HeightMap,
        warnings: &mut Vec<String>,
        observer: &dyn Observer,
    ) -> SetupResult<Option<ScenarioOperators>> {
        if self.settings.operator == OperatorChoice::Sparse {
            return Ok(None);
        }
        let mut notes = Vec::new();
        let Some((nominal, build)) = self.lattice_operator(rows, &mut notes)? else {
            warnings.extend(notes);
            return Ok(None);
        };
        warnings.extend(notes);
        let Some(pitch_mm) = FftOperator::lattice_pitch_mm(rows.x_mm(), rows.y_mm()) else {
            return Ok(None);
        };
        let mut blocks: Vec<Box<dyn InfluenceOperator>> =
            Vec::with_capacity(robust::SCENARIO_COUNT);
        let mut nominal = Some(nominal);
        for (s, scenario) in self.robust_scenarios().iter().enumerate() {
            let tif = PerturbedTif::new(&self.tif, scenario.width_factor, 1.0, scenario.offset_mm);
            // The nominal scenario's notes are the plan's; the others' repeat them.
            let mut scenario_notes = Vec::new();
            let notes = if s == 0 {
                &mut *warnings
            } else {
                &mut scenario_notes
            };
            let block =
                self.lattice_block(rows, build, pitch_mm, &tif, nominal.take(), notes, observer)?;
            // A scenario's own notes (its operator's error) are kept once.
            for note in scenario_notes {
                if note.starts_with("robust:") && !warnings.contains(&note) {
                    warnings.push(note);
                }
            }
            match block {
                Some(op) => blocks.push(op),
                None => return Ok(None),
            }
        }
        Ok(Some(Arc::from(blocks)))
    }

    /// The lattice operator `build` over `rows` on the lattice of `pitch_mm` with the kernel of
    /// `tif` (swept along the dominant stretch under the swept model), with its exact swept
    /// columns where stretches differ; `built`, when given, is that operator already built with
    /// the kernel. `None` where the swept columns would be assembled instead. An approximate
    /// operator whose measured error with this kernel exceeds its design tolerance says so in
    /// `notes`.
    #[allow(clippy::too_many_arguments)]
    pub(super) fn lattice_block(
        &self,
        rows: &HeightMap,
        build: LatticeBuild,
        pitch_mm: f64,
        tif: &PerturbedTif<'_, Tif>,
        built: Option<Box<dyn InfluenceOperator>>,
        notes: &mut Vec<String>,
        observer: &dyn Observer,
    ) -> SetupResult<Option<Box<dyn InfluenceOperator>>> {
        let swept_kernel = self.shared_kernel(tif);
        let kernel: &dyn InfluenceFunction = match &swept_kernel {
            Some(k) => k,
            None => tif,
        };
        let op = match built {
            Some(op) => op,
            None => self
                .lattice_with_kernel(rows, build, pitch_mm, kernel, notes)
                .at(SetupInput::Map)?,
        };
        self.swept_corrected(op, rows, tif, kernel, notes, observer)
    }

    /// `tif` swept along the dominant stretch under the swept model (the lattice operators'
    /// shared kernel); `None` under the point model, where the kernel is `tif` itself.
    pub(super) fn shared_kernel<'a>(
        &self,
        tif: &PerturbedTif<'a, Tif>,
    ) -> Option<SweptTif<PerturbedTif<'a, Tif>>> {
        self.swept
            .as_ref()
            .map(|(stretches, _)| stretches.dominant_kernel(tif.clone()))
    }

    /// The lattice operator `build` over `rows` and the dwell points, map on the lattice of
    /// `pitch_mm`, with the shift-invariant `kernel` at every dwell point. An approximate
    /// operator (NUFFT, spreading) whose estimated error with `kernel` is above its design
    /// tolerance says so in `notes`.
    fn lattice_with_kernel(
        &self,
        rows: &HeightMap,
        build: LatticeBuild,
        pitch_mm: f64,
        kernel: &dyn InfluenceFunction,
        notes: &mut Vec<String>,
    ) -> crate::error::Result<Box<dyn InfluenceOperator>> {
        let (mx, my, dx, dy) = (rows.x_mm(), rows.y_mm(), self.path.x_mm(), self.path.y_mm());
        let mut above = |name: &str, error: f64, tolerance: f64| {
            if error > tolerance {
                notes.push(format!(
                    "robust: a scenario's {name} operator has an estimated error of {error:.1e}, \
                     above {tolerance:.0e}; the residuals reported are the exact R's"
                ));
            }
        };
        Ok(match build {
            LatticeBuild::Fft => Box::new(FftOperator::new(mx, my, dx, dy, pitch_mm, kernel)?),
            LatticeBuild::Stencil => {
                Box::new(StencilOperator::new(mx, my, dx, dy, pitch_mm, kernel)?)
            }
            LatticeBuild::Nufft {
                refinement,
                tolerance,
            } => {
                let op =
                    NufftOperator::new(mx, my, dx, dy, pitch_mm, refinement, tolerance, kernel)?;
                above("NUFFT", op.estimated_error(), tolerance);
                Box::new(op)
            }
            LatticeBuild::Spread { oversampling } => {
                let op = SpreadOperator::new(mx, my, dx, dy, pitch_mm, oversampling, kernel)?;
                above(
                    "spreading",
                    op.estimated_error(),
                    self.settings.spread_tolerance,
                );
                Box::new(op)
            }
        })
    }

    /// The robust plan's problem over `rows` ([`robust`]) and its scenario weights: the
    /// scenarios' operators ([`Setup::robust_lattice_blocks`], else their assembled matrices)
    /// stacked against the target repeated, `rho` and `lambda` times the scenario count, the
    /// rows of block `s` scaled by `sqrt(w_s)` (equal weights: the mean over the scenarios;
    /// `robust_weighting = "minimax"`: the weights of [`robust::minimax_weights`], whose rounds
    /// solve the weighted problem here). On a curved part each scenario's matrix is assembled in
    /// the tangent frames ([`Setup::assemble_scenario`]).
    pub(super) fn robust_problem(
        &self,
        rows: &HeightMap,
        warnings: &mut Vec<String>,
        observer: &dyn Observer,
    ) -> SetupResult<(Problem, Vec<f64>)> {
        let scenarios = robust::SCENARIO_COUNT;
        let u = &self.tool_uncertainty;
        let described = format!(
            "nominal, TIF {:.1}% wider and narrower, tool {:.3} mm off either way in x and {:.3} mm in y: one standard deviation of the tool's uncertainty",
            100.0 * u.width_sigma,
            u.offset_x_sigma_mm,
            u.offset_y_sigma_mm
        );
        let what = match self.settings.robust_weighting {
            crate::dwell::RobustWeighting::Mean => "mean",
            crate::dwell::RobustWeighting::Minimax => "worst",
        };
        let stack = match self.robust_lattice_blocks(rows, warnings, observer)? {
            Some(blocks) => {
                warnings.push(format!(
                    "robust: the plan minimises the {what} residual over {scenarios} scenarios \
                     ({described}), each scenario's {} operator stacked (matrix-free)",
                    kind_label(blocks[0].kind())
                ));
                RobustStack::Operators(blocks)
            }
            None => {
                let blocks = self
                    .robust_scenarios()
                    .iter()
                    .map(|s| self.assemble_scenario(rows, &s.perturbation(), observer))
                    .collect::<SetupResult<Vec<_>>>()?;
                let stacked = crate::influence::operator::stacked::stack_rows(&blocks)
                    .at(SetupInput::None)?;
                warnings.push(format!(
                    "robust: the plan minimises the {what} residual over {scenarios} scenarios \
                     ({described}), {:.2e} non-zeros in the stacked R",
                    stacked.nnz() as f64
                ));
                RobustStack::Matrix(Box::new(stacked))
            }
        };
        let s = scenarios as f64;
        let weighted = |weights: &[f64]| -> crate::error::Result<Problem> {
            let target = robust::weighted_target(rows.z_nm(), weights);
            let (bounds, rho, lambda) = (self.bounds.clone(), self.rho * s, self.lambda * s);
            match &stack {
                RobustStack::Matrix(stacked) => Problem::new(
                    robust::weighted_rows(stacked, weights)?,
                    target,
                    bounds,
                    rho,
                    lambda,
                ),
                RobustStack::Operators(blocks) => Problem::new(
                    StackedRows::new(
                        Arc::clone(blocks),
                        weights.iter().map(|w| w.sqrt()).collect(),
                    )?,
                    target,
                    bounds,
                    rho,
                    lambda,
                ),
            }?
            .with_dwell_lattice(DwellLattice::detect(self.path.x_mm(), self.path.y_mm()))?
            .with_scenario_scales(weights.iter().map(|w| w.sqrt()).collect())
        };
        // Every scenario's removal `[R_1 t; ...; R_S t]`, unweighted.
        let removal = |t: &[f64]| -> crate::error::Result<Vec<f64>> {
            match &stack {
                RobustStack::Matrix(stacked) => stacked.removal_nm(t),
                RobustStack::Operators(blocks) => {
                    StackedRows::new(Arc::clone(blocks), vec![1.0; scenarios])?.removal_nm(t)
                }
            }
        };
        let weights = match self.settings.robust_weighting {
            crate::dwell::RobustWeighting::Mean => vec![1.0; scenarios],
            crate::dwell::RobustWeighting::Minimax => {
                let time_nm2_per_s = self.time_weight_nm2_per_s();
                let rounds = robust::minimax_weights(scenarios, time_nm2_per_s, |weights, warm| {
                    let problem = weighted(weights)?;
                    let warm = warm.or(self.warm_start_s.as_deref());
                    let plan =
                        crate::dwell::solve_validated(&problem, &self.settings, observer, warm)?;
                    let rms = robust::scenario_rms_nm(self.map.z_nm(), &removal(&plan.dwell_s)?);
                    Ok((plan.dwell_s, rms))
                })
                .at(SetupInput::None)?;
                let best = rounds
                    .worst_rms_nm
                    .iter()
                    .copied()
                    .fold(f64::INFINITY, f64::min);
                let equal = rounds.worst_rms_nm.first().copied().unwrap_or(f64::NAN);
                let listed: Vec<String> =
                    rounds.weights.iter().map(|w| format!("{w:.3}")).collect();
                warnings.push(format!(
                    "robust minimax: scenario weights {} after {} solves; worst scenario as \
                     planned {best:.4} nm (equal weights: {equal:.4} nm); its worst mean square \
                     plus time term {:.1}% above the rounds' duality bound",
                    listed.join(", "),
                    rounds.worst_rms_nm.len(),
                    100.0 * rounds.duality_gap,
                ));
                rounds.weights
            }
        };
        let problem = weighted(&weights).at(SetupInput::Job)?;
        Ok((problem, weights))
    }
}

/// How the robust plan's scenarios are held: matrix-free blocks or the stacked assembled `R`.
enum RobustStack {
    /// Each scenario's lattice operator.
    Operators(ScenarioOperators),
    /// `[R_1; ...; R_S]` assembled.
    Matrix(Box<InfluenceMatrix>),
}

/// The operator's name in the notes.
fn kind_label(kind: OperatorKind) -> &'static str {
    match kind {
        OperatorKind::Sparse => "assembled",
        OperatorKind::Fft => "FFT",
        OperatorKind::FftSpread => "spreading",
        OperatorKind::Stencil => "stencil",
        OperatorKind::Nufft => "NUFFT",
        OperatorKind::Expansion => "direction expansion",
    }
}
