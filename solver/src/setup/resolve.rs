//! [`Setup::resolve`]: the checked choices and the data made into a set-up (dwell points, bounds,
//! swept stretches, warm start), validated once.

use super::choices::WARM_START_WITH_ACCEL;
use super::*;
use crate::influence::operator::lattice::lattice_index;
use crate::influence::operator::stencil::lattice_origin;
use crate::path::raster::RasterPlacement;

/// Values held per dwell point through a solve (path, lengths, dwell, feeds, solver work
/// vectors), not counting the influence matrix: the memory budget's lower bound.
pub(super) const DWELL_POINT_VALUES: f64 = 16.0;

/// The regular lattice the map's points lie on, if any: its pitch, mm, and the node through the
/// map's lowest x and y (the lattice the FFT and phase-stencil operators use).
fn map_lattice(map: &HeightMap) -> Option<(f64, [f64; 2])> {
    let (x, y) = (map.x_mm(), map.y_mm());
    let h = FftOperator::lattice_pitch_mm(x, y)?;
    let (x0, y0) = lattice_origin(x, y);
    let origin = [x0, y0];
    let on = x.iter().zip(y).all(|(&x, &y)| {
        lattice_index(x, origin[0], h).is_some() && lattice_index(y, origin[1], h).is_some()
    });
    on.then_some((h, origin))
}

impl Setup {
    /// Resolves the data under the checked choices: the dwell points (generating the raster),
    /// the dwell bounds and the warm start's length. Given points with feed limits are at least
    /// two (a path of length zero has no feed); without limits (a plan evaluated as given,
    /// [`Setup::removal_of`]) one point is a spot.
    pub fn resolve(
        checked: Checked,
        data: SetupData,
        observer: &dyn Observer,
    ) -> SetupResult<Self> {
        observer.setup_step(SetupStep::Resolve);
        let Checked {
            choices,
            accel,
            corner_angle_deg,
        } = checked;
        let SetupData {
            map,
            tif,
            dwell,
            surface,
            warm_start_s,
        } = data;
        if warm_start_s.is_some() && accel.is_some() {
            return Err(Error::invalid("warm_start", WARM_START_WITH_ACCEL)).at(SetupInput::Job);
        }
        if matches!(choices.tif_model, TifModel::CurvatureDependent(_)) && surface.is_none() {
            return Err(Error::invalid(
                "curvature-dependent TIF",
                "needs a design surface ([surface] file or --surface)",
            ))
            .at(SetupInput::Job);
        }
        if let Some(s) = &surface {
            s.validate().at(SetupInput::Surface)?;
        }
        let mut raster_placement = None;
        let path = match dwell {
            DwellPoints::Given(p) => {
                // A plan to solve for needs feeds; one evaluated as given (no limits) may be a
                // single spot.
                if p.len() < 2 && choices.feed.is_some() {
                    return Err(Error::invalid(
                        "dwell points",
                        "one dwell point: a path of length zero has no feed; give at least two \
                         points",
                    ))
                    .at(SetupInput::Dwell);
                }
                p
            }
            DwellPoints::Raster { pitch_mm, along } => {
                let bbox = map
                    .bounding_box_mm()
                    .ok_or_else(|| Error::invalid("map", "no data rows"))
                    .at(SetupInput::Map)?
                    .expanded(tif.nominal_radius_mm());
                if pitch_mm.is_finite() && pitch_mm > 0.0 {
                    let points = ((bbox.x_max_mm - bbox.x_min_mm) / pitch_mm + 1.0)
                        * ((bbox.y_max_mm - bbox.y_min_mm) / pitch_mm + 1.0);
                    crate::budget::check_f64s(
                        "--raster-pitch-mm",
                        &format!(
                            "a raster of pitch {pitch_mm} mm over the map plus the TIF radius \
                             ({points:.3e} dwell points, at least {DWELL_POINT_VALUES} values each)"
                        ),
                        points,
                        DWELL_POINT_VALUES,
                    )
                    .at(SetupInput::None)?;
                }
                let lattice = map_lattice(&map);
                let bbox = match lattice {
                    Some((h, origin)) => raster::snapped_to_lattice(&bbox, h, origin),
                    None => bbox,
                };
                let origin_mm = [bbox.x_min_mm, bbox.y_min_mm];
                raster_placement = Some(RasterPlacement {
                    pitch_mm,
                    origin_mm,
                    map_lattice_pitch_mm: lattice.map(|(h, _)| h),
                    phase_cells: lattice
                        .map(|(h, origin)| raster::lattice_phase_cells(origin_mm, h, origin)),
                });
                raster::serpentine(&bbox, pitch_mm, along).at(SetupInput::Job)?
            }
        };
        let ds_mm = path.ds_mm();
        let bounds = match &choices.feed {
            Some(feed) => DwellBounds::from_feeds(&ds_mm, feed),
            None => DwellBounds::new(vec![0.0; path.len()], None),
        }
        .at(SetupInput::Job)?;
        if let Some(w) = &warm_start_s {
            if w.len() != path.len() {
                return Err(Error::invalid(
                    "warm start",
                    format!(
                        "has {} dwell times but the job has {} dwell points",
                        w.len(),
                        path.len()
                    ),
                ))
                .at(SetupInput::WarmStart);
            }
        }
        // The swept model in the plane and on a curved part (each stretch in its dwell point's
        // tangent frame, with the dwell point's own TIF where it depends on the curvature): a
        // given plan evaluated (no feed limits) keeps the point model, whose `R t` simulate's
        // discrete motion is.
        let swept = match (choices.settings.influence, &choices.feed) {
            (InfluenceModel::Swept, Some(_)) => {
                let stretches = Stretches::of_path(&path, default_sample_step_mm(&tif))
                    .at(SetupInput::Dwell)?;
                let kernel = stretches.dominant_kernel(tif.clone());
                Some((stretches, kernel))
            }
            _ => None,
        };
        Ok(Self {
            swept,
            raster: raster_placement,
            rate_drift_per_hour: 0.0,
            tool_uncertainty: crate::calibrate::ToolUncertainty::default(),
            map,
            tif,
            tif_model: choices.tif_model,
            path,
            ds_mm,
            surface,
            tif_frame: choices.tif_frame,
            feed: choices.feed,
            bounds,
            accel,
            corner_angle_deg,
            rho: choices.rho,
            lambda: choices.lambda,
            settings: choices.settings,
            edge: choices.edge,
            warm_start_s,
        })
    }

    /// The influence model the plan uses: swept where the set-up built it (a solve with feed
    /// limits, unless the job asks for the point model), the point model otherwise.
    pub fn influence_model(&self) -> InfluenceModel {
        if self.swept.is_some() {
            InfluenceModel::Swept
        } else {
            InfluenceModel::Point
        }
    }
}
