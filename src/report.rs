//! Plots of an identification (`jointid replay --plots DIR`), as SVG files a browser or a
//! report can show:
//!
//! - `loop-<connection>.svg`: the force–deformation loop, the connection force the estimator
//!   inferred at every sample against the deformation δ, with the identified law evaluated at
//!   the same states. A friction joint shows a hysteresis loop, a spring a line; where the
//!   two clouds part, the law misses something.
//! - `response-<sensor>.svg`: the measured response and the response the identified model
//!   predicts from the measured excitation alone (simulation, not one-step prediction), with
//!   the fit percentage `100 (1 − ‖y − ŷ‖ / ‖y − ȳ‖)` (what MATLAB's `compare` reports).
//! - `parameters.svg`: every parameter per pass with its 95 % interval, and the truth when
//!   the recording holds it: whether the passes converged and to what.
//!
//! Long records are thinned to at most [`MAX_POINTS`] points per series (evenly strided) so
//! a file stays a few hundred kB. Why SVG: the `plotters` crate writes it with no system
//! library (fonts or image codecs), so plotting works on any machine the tool builds on.

use std::collections::BTreeMap;
use std::path::{Path, PathBuf};

use plotters::prelude::*;
use serde::Serialize;

use crate::estimate::StepOutput;
use crate::estimate::ml::{self, Discretisation};
use crate::identify::{Identification, TestData};
use crate::model::Model;
use crate::setup::{Basis, Setup};

/// One series of a plot: legend label, points, colour.
type Series<'a> = (String, &'a [(f64, f64)], RGBColor);

/// Most points drawn per series.
pub const MAX_POINTS: usize = 4_000;

#[derive(Debug, thiserror::Error)]
pub enum ReportError {
    #[error("{path}: {source}")]
    Io {
        path: PathBuf,
        source: std::io::Error,
    },
    #[error("{path}: drawing failed: {what}")]
    Draw { path: PathBuf, what: String },
}

/// What [`write_plots`] wrote.
#[derive(Debug, Clone, Default, Serialize)]
pub struct PlotSummary {
    pub files: Vec<PathBuf>,
    /// Per sensor: fit percentage of the predicted response (absent when the prediction
    /// could not be computed, see `notes`).
    pub fit_percent: BTreeMap<String, f64>,
    pub notes: Vec<String>,
}

/// Fit percentage `100 (1 − ‖y − ŷ‖ / ‖y − ȳ‖)`: 100 is perfect, 0 no better than the mean,
/// negative worse.
pub fn fit_percent(measured: &[f64], predicted: &[f64]) -> f64 {
    let n = measured.len().min(predicted.len());
    if n == 0 {
        return f64::NAN;
    }
    let mean = measured[..n].iter().sum::<f64>() / n as f64;
    let err: f64 = (0..n).map(|i| (measured[i] - predicted[i]).powi(2)).sum();
    let spread: f64 = measured[..n].iter().map(|y| (y - mean).powi(2)).sum();
    if spread == 0.0 {
        return if err == 0.0 { 100.0 } else { f64::NEG_INFINITY };
    }
    100.0 * (1.0 - (err / spread).sqrt())
}

/// The identified model's response to the measured excitation (sensor-major: `[sensor][i]`),
/// on the model the identification used ([`Model::for_identification`], so a reduced
/// model's estimated initial state fits it). Maximum likelihood predicts with its own
/// discretisation and estimated initial state; the other estimators from rest with the
/// sub-steps of the output-error refinement when it ran, else the setup's. `Err` says why
/// there is no prediction (a failed identification, a diverging simulation).
pub fn predicted_response(
    setup: &Setup,
    data: &TestData,
    identification: &Identification,
) -> Result<Vec<Vec<f64>>, String> {
    let model = &Model::for_identification(setup).map_err(|e| e.to_string())?;
    let m = setup.sensors.len();
    let rows: Vec<Vec<f64>> = if let Some(fit) = &identification.maximum_likelihood {
        let d = Discretisation {
            scheme: fit.scheme,
            substeps: fit.substeps,
        };
        // The excitation as the fit read it between samples.
        let smoothed;
        let data = if fit.between == ml::Between::Smooth {
            smoothed = TestData {
                excitation: crate::estimate::moment_matched(&data.excitation),
                ..data.clone()
            };
            &smoothed
        } else {
            data
        };
        let tr = ml::predict(setup, model, data, &fit.params, Some(&fit.initial_state), d)
            .map_err(|e| e.to_string())?;
        tr.y.chunks(m).map(<[f64]>::to_vec).collect()
    } else {
        let params: Vec<f64> = identification
            .final_parameters()
            .ok_or("no parameters were identified")?
            .iter()
            .map(|p| p.value)
            .collect();
        let substeps = identification
            .output_error
            .as_ref()
            .map_or(setup.substeps, |o| o.substeps.max(1));
        match &identification.initial_state {
            // A record in motion: the free run from the estimated initial state (the
            // observer form with a zero gain).
            Some(x0) => crate::simulate::predictions_with_observer(
                setup,
                model,
                &params,
                &data.excitation,
                &data.response,
                setup.dt_s,
                substeps,
                &nalgebra::DMatrix::zeros(3 * model.n(), m),
                Some(x0),
            ),
            None => crate::simulate::response_to_excitation(
                setup,
                model,
                &params,
                &data.excitation,
                setup.dt_s,
                substeps,
            ),
        }
        .map_err(|e| e.to_string())?
    };
    Ok((0..m)
        .map(|j| {
            rows.iter()
                .map(|r| r.get(j).copied().unwrap_or(f64::NAN))
                .collect()
        })
        .collect())
}

/// Writes the plots into `dir` (created if needed); see the module docs. `prediction` is
/// [`predicted_response`]'s result (computed once by the caller, which also records it).
pub fn write_plots(
    dir: &Path,
    setup: &Setup,
    data: &TestData,
    identification: &Identification,
    last_pass: &[(usize, StepOutput)],
    truth: &BTreeMap<String, f64>,
    prediction: &Result<Vec<Vec<f64>>, String>,
) -> Result<PlotSummary, ReportError> {
    std::fs::create_dir_all(dir).map_err(|source| ReportError::Io {
        path: dir.to_path_buf(),
        source,
    })?;
    let mut summary = PlotSummary::default();
    let t0 = data.t_ns.first().copied().unwrap_or(0);
    let time_s: Vec<f64> = data.t_ns.iter().map(|&t| (t - t0) as f64 * 1e-9).collect();

    // Force–deformation loops (from the last pass's per-sample estimates; a windowed
    // identification keeps none).
    let finals = identification.final_parameters().unwrap_or(&[]);
    let mut offset = 0;
    if last_pass.is_empty() {
        summary.notes.push(
            "force–deformation loops not drawn: no per-sample residual-force estimate was kept (a windowed identification keeps none)".into(),
        );
    }
    for (c, conn) in setup
        .connections
        .iter()
        .enumerate()
        .filter(|_| !last_pass.is_empty())
    {
        let k = conn.basis.len();
        let params: Vec<f64> = finals
            .get(offset..offset + k)
            .map(|p| p.iter().map(|e| e.value).collect())
            .unwrap_or_default();
        offset += k;
        let mut estimated = Vec::with_capacity(last_pass.len());
        let mut law = Vec::with_capacity(last_pass.len());
        for (_, o) in thin(last_pass) {
            let (d, v, a) = (o.delta[c], o.delta_v[c], o.delta_a[c]);
            estimated.push((d, o.force[c]));
            if params.len() == k {
                let f: f64 = conn
                    .basis
                    .iter()
                    .zip(&params)
                    .map(|(b, p)| p * b.eval(d, v, a))
                    .sum();
                law.push((d, f));
            }
        }
        let path = dir.join(format!("loop-{}.svg", file_name(&conn.name)));
        let basis: Vec<String> = conn.basis.iter().map(|b| b.label()).collect();
        let law_label = format!("identified law ({})", basis.join(" + "));
        scatter_plot(
            &path,
            &format!("{}: connection force against deformation", conn.name),
            "deformation δ (m)",
            "connection force (N, positive resisting)",
            &[
                ("estimated from the data".to_string(), &estimated, BLUE),
                (law_label.clone(), &law, RED),
            ],
        )?;
        summary.files.push(path);
        // A stiffness term hides friction and damping an order of magnitude smaller: the
        // same loop without the identified `u` term shows them (a friction step, a
        // damping ellipse).
        if let Some(ku) = conn
            .basis
            .iter()
            .position(|b| matches!(b, Basis::U))
            .and_then(|j| params.get(j).copied())
            && conn.basis.len() > 1
        {
            let less = |pts: &[(f64, f64)]| -> Vec<(f64, f64)> {
                pts.iter().map(|&(d, f)| (d, f - ku * d)).collect()
            };
            let path = dir.join(format!(
                "loop-{}-without-stiffness.svg",
                file_name(&conn.name)
            ));
            scatter_plot(
                &path,
                &format!(
                    "{}: force less the identified stiffness ({ku:.4e} N/m × δ)",
                    conn.name
                ),
                "deformation δ (m)",
                "connection force − k δ (N)",
                &[
                    (
                        "estimated from the data".to_string(),
                        &less(&estimated),
                        BLUE,
                    ),
                    (law_label, &less(&law), RED),
                ],
            )?;
            summary.files.push(path);
        }
    }

    // Measured against predicted response.
    let predicted = match prediction {
        Ok(p) => Some(p),
        Err(why) => {
            summary.notes.push(format!("no predicted response: {why}"));
            None
        }
    };
    for (j, sensor) in setup.sensors.iter().enumerate() {
        let measured: Vec<f64> = data.response.iter().map(|r| r[j]).collect();
        let mut series = vec![(
            "measured".to_string(),
            thin_xy(&time_s, &measured),
            RGBColor(90, 90, 90),
        )];
        let mut title = format!("{}: measured and predicted response", sensor.name);
        if let Some(p) = predicted.as_ref().and_then(|p| p.get(j)) {
            let fit = fit_percent(&measured, p);
            summary.fit_percent.insert(sensor.name.clone(), fit);
            title = format!("{title} (fit {fit:.1} %)");
            series.push((
                "predicted by the identified model".to_string(),
                thin_xy(&time_s, p),
                RED,
            ));
        }
        let path = dir.join(format!("response-{}.svg", file_name(&sensor.name)));
        let series: Vec<Series<'_>> = series
            .iter()
            .map(|(l, s, c)| (l.clone(), s.as_slice(), *c))
            .collect();
        line_plot(
            &path,
            &title,
            "time (s)",
            &format!("{} ({})", sensor.name, sensor.unit),
            &series,
        )?;
        summary.files.push(path);
    }

    // Parameters per pass.
    if !identification.passes.is_empty() {
        let path = dir.join("parameters.svg");
        parameter_plot(&path, setup, identification, truth)?;
        summary.files.push(path);
    }
    Ok(summary)
}

/// A file-name-safe version of a channel or connection name.
fn file_name(name: &str) -> String {
    name.chars()
        .map(|c| {
            if c.is_ascii_alphanumeric() || c == '-' || c == '_' || c == '.' {
                c
            } else {
                '_'
            }
        })
        .collect()
}

fn stride(n: usize) -> usize {
    n.div_ceil(MAX_POINTS).max(1)
}

fn thin<T>(items: &[T]) -> impl Iterator<Item = &T> {
    items.iter().step_by(stride(items.len()))
}

fn thin_xy(x: &[f64], y: &[f64]) -> Vec<(f64, f64)> {
    let n = x.len().min(y.len());
    (0..n)
        .step_by(stride(n))
        .map(|i| (x[i], y[i]))
        .filter(|(a, b)| a.is_finite() && b.is_finite())
        .collect()
}

/// Range of the points with a 5 % margin (a flat series gets a unit-wide range).
fn range(
    points: impl Iterator<Item = (f64, f64)>,
) -> Option<(std::ops::Range<f64>, std::ops::Range<f64>)> {
    let (mut x0, mut x1, mut y0, mut y1) = (
        f64::INFINITY,
        f64::NEG_INFINITY,
        f64::INFINITY,
        f64::NEG_INFINITY,
    );
    for (x, y) in points.filter(|(x, y)| x.is_finite() && y.is_finite()) {
        x0 = x0.min(x);
        x1 = x1.max(x);
        y0 = y0.min(y);
        y1 = y1.max(y);
    }
    if !x0.is_finite() {
        return None;
    }
    let pad = |a: f64, b: f64| {
        let w = if b > a {
            (b - a) * 0.05
        } else {
            a.abs().max(1e-12) * 0.5
        };
        (a - w)..(b + w)
    };
    Some((pad(x0, x1), pad(y0, y1)))
}

/// A tick label: 4 significant digits, round-off next to zero shown as 0.
fn tick(v: f64, width: f64) -> String {
    if v.abs() < 1e-9 * width.abs() {
        "0".to_string()
    } else {
        format!("{v:.3e}")
    }
}

fn draw_error(path: &Path) -> impl Fn(String) -> ReportError + '_ {
    move |what| ReportError::Draw {
        path: path.to_path_buf(),
        what,
    }
}

/// How a plot draws its series.
#[derive(Clone, Copy, PartialEq)]
enum Marks {
    /// Dots (a loop: the points have no order that a line could follow).
    Points,
    /// Lines (a time history).
    Lines,
}

fn scatter_plot(
    path: &Path,
    title: &str,
    x_label: &str,
    y_label: &str,
    series: &[Series<'_>],
) -> Result<(), ReportError> {
    xy_plot(
        path,
        (900, 600),
        title,
        x_label,
        y_label,
        series,
        Marks::Points,
    )
}

fn line_plot(
    path: &Path,
    title: &str,
    x_label: &str,
    y_label: &str,
    series: &[Series<'_>],
) -> Result<(), ReportError> {
    xy_plot(
        path,
        (1000, 500),
        title,
        x_label,
        y_label,
        series,
        Marks::Lines,
    )
}

fn xy_plot(
    path: &Path,
    size: (u32, u32),
    title: &str,
    x_label: &str,
    y_label: &str,
    series: &[Series<'_>],
    marks: Marks,
) -> Result<(), ReportError> {
    let err = draw_error(path);
    let root = SVGBackend::new(path, size).into_drawing_area();
    root.fill(&WHITE).map_err(|e| err(e.to_string()))?;
    let all = series.iter().flat_map(|(_, s, _)| s.iter().copied());
    let Some((xr, yr)) = range(all) else {
        return Err(err("no finite points to draw".into()));
    };
    let (x_width, y_width) = (xr.end - xr.start, yr.end - yr.start);
    let mut chart = ChartBuilder::on(&root)
        .caption(title, ("sans-serif", 20))
        .margin(15)
        .x_label_area_size(45)
        .y_label_area_size(80)
        .build_cartesian_2d(xr, yr)
        .map_err(|e| err(e.to_string()))?;
    let y_ticks = |v: &f64| tick(*v, y_width);
    // A time axis reads best in plain decimals; a deformation axis needs exponents.
    let x_ticks = |v: &f64| match marks {
        Marks::Points => tick(*v, x_width),
        Marks::Lines => {
            let text = format!("{v:.6}");
            text.trim_end_matches('0').trim_end_matches('.').to_string()
        }
    };
    chart
        .configure_mesh()
        .x_desc(x_label)
        .y_desc(y_label)
        .x_label_formatter(&x_ticks)
        .y_label_formatter(&y_ticks)
        .draw()
        .map_err(|e| err(e.to_string()))?;
    for (label, points, color) in series {
        if points.is_empty() {
            continue;
        }
        let color = *color;
        let drawn = match marks {
            Marks::Points => {
                let radius = if series.len() > 1 && color == RED {
                    1
                } else {
                    3
                };
                chart
                    .draw_series(
                        points
                            .iter()
                            .map(move |&p| Circle::new(p, radius, color.filled())),
                    )
                    .map_err(|e| err(e.to_string()))?
            }
            Marks::Lines => chart
                .draw_series(LineSeries::new(
                    points.iter().copied(),
                    color.stroke_width(1),
                ))
                .map_err(|e| err(e.to_string()))?,
        };
        drawn.label(label.as_str()).legend(move |(x, y)| {
            PathElement::new(vec![(x, y), (x + 20, y)], color.stroke_width(3))
        });
    }
    chart
        .configure_series_labels()
        .background_style(WHITE.mix(0.85))
        .border_style(BLACK)
        .position(if marks == Marks::Points {
            SeriesLabelPosition::UpperLeft
        } else {
            SeriesLabelPosition::UpperRight
        })
        .draw()
        .map_err(|e| err(e.to_string()))?;
    root.present().map_err(|e| err(e.to_string()))
}

/// One panel per parameter: value per pass with its 95 % interval, truth dashed.
fn parameter_plot(
    path: &Path,
    setup: &Setup,
    identification: &Identification,
    truth: &BTreeMap<String, f64>,
) -> Result<(), ReportError> {
    let err = draw_error(path);
    let keys = setup.param_keys();
    let panels = keys.len().max(1);
    let root = SVGBackend::new(path, (900, (220 * panels) as u32 + 40)).into_drawing_area();
    root.fill(&WHITE).map_err(|e| err(e.to_string()))?;
    let root = root
        .titled(
            "parameters per pass (95 % intervals; truth in green where known)",
            ("sans-serif", 20),
        )
        .map_err(|e| err(e.to_string()))?;
    let areas = root.split_evenly((panels, 1));
    for (k, (key, area)) in keys.iter().zip(areas.iter()).enumerate() {
        let points: Vec<(f64, f64, f64, f64)> = identification
            .passes
            .iter()
            .filter_map(|p| {
                let e = p.parameters.get(k)?;
                Some((p.pass as f64, e.value, e.ci95[0], e.ci95[1]))
            })
            .filter(|(_, v, lo, hi)| v.is_finite() && lo.is_finite() && hi.is_finite())
            .collect();
        let truth_value = truth.get(key).copied();
        let extent = points
            .iter()
            .flat_map(|&(x, _, lo, hi)| [(x, lo), (x, hi)])
            .chain(truth_value.map(|t| (points.first().map_or(1.0, |p| p.0), t)));
        let Some((mut xr, yr)) = range(extent) else {
            continue;
        };
        xr = (xr.start.min(0.5))..(xr.end.max(points.len() as f64 + 0.5));
        let unit = identification
            .final_parameters()
            .and_then(|f| f.get(k))
            .map(|e| e.unit.clone())
            .unwrap_or_default();
        let y_width = yr.end - yr.start;
        let mut chart = ChartBuilder::on(area)
            .margin(10)
            .x_label_area_size(35)
            .y_label_area_size(80)
            .caption(format!("{key} ({unit})"), ("sans-serif", 16))
            .build_cartesian_2d(xr.clone(), yr)
            .map_err(|e| err(e.to_string()))?;
        chart
            .configure_mesh()
            .x_desc("pass")
            .x_label_formatter(&|v| format!("{v:.0}"))
            .y_label_formatter(&|v| tick(*v, y_width))
            .draw()
            .map_err(|e| err(e.to_string()))?;
        chart
            .draw_series(
                points
                    .iter()
                    .map(|&(x, v, lo, hi)| ErrorBar::new_vertical(x, lo, v, hi, BLUE.filled(), 8)),
            )
            .map_err(|e| err(e.to_string()))?;
        if let Some(t) = truth_value {
            chart
                .draw_series(LineSeries::new(
                    [(xr.start, t), (xr.end, t)],
                    GREEN.stroke_width(1),
                ))
                .map_err(|e| err(e.to_string()))?;
        }
    }
    root.present().map_err(|e| err(e.to_string()))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn fit_percent_is_100_for_a_perfect_prediction_and_0_for_the_mean() {
        let y = [1.0, -2.0, 3.0, 0.5];
        assert_eq!(fit_percent(&y, &y), 100.0);
        let mean = y.iter().sum::<f64>() / 4.0;
        assert!(fit_percent(&y, &[mean; 4]).abs() < 1e-12);
        assert!(fit_percent(&y, &[-1.0, 2.0, -3.0, -0.5]) < 0.0);
    }

    #[test]
    fn thinning_keeps_at_most_max_points() {
        let x: Vec<f64> = (0..100_001).map(f64::from).collect();
        let thinned = thin_xy(&x, &x);
        assert!(thinned.len() <= MAX_POINTS && thinned.len() > MAX_POINTS / 2);
        assert_eq!(thinned[0], (0.0, 0.0));
    }
}
