//! The evaluation's pictures as PNG files: the reward heatmap over a maze, a job's loss curve
//! and reward histograms.
//!
//! Drawing is plotters' bitmap backend into an RGB buffer, encoded with `png`. Text uses
//! DejaVu Sans compiled into the binary (the `dejavu` crate) and registered with plotters'
//! `ab_glyph` font loader, so titles, axis labels and tick labels render on a machine with no
//! fonts installed (plotters' default `ttf` feature would look them up through fontconfig).

use std::error::Error;
use std::fs::File;
use std::io::BufWriter;
use std::path::Path;
use std::sync::Once;

use plotters::coord::Shift;
use plotters::prelude::*;
use plotters::style::colors::colormaps::ViridisRGB;

use super::heatmap::Grid;

/// Size of every picture.
pub const WIDTH: u32 = 900;
pub const HEIGHT: u32 = 700;

const FONT: &str = "sans-serif";
const TITLE_SIZE: u32 = 24;
const LABEL_SIZE: u32 = 18;
const TICK_SIZE: u32 = 15;
/// Bins without enough data.
const MASKED: RGBColor = RGBColor(222, 222, 222);
const WALL: RGBColor = RGBColor(60, 60, 60);
/// Series colours (matplotlib's first two) for loss curves and histograms.
const SERIES: [RGBColor; 4] =
    [RGBColor(31, 119, 180), RGBColor(255, 127, 14), RGBColor(44, 160, 44), RGBColor(214, 39, 40)];

/// A picture that could not be drawn or written.
#[derive(Debug, thiserror::Error)]
#[error("{0}")]
pub struct PlotError(String);

type Drawn = Result<(), Box<dyn Error>>;

fn register_fonts() {
    static FONTS: Once = Once::new();
    FONTS.call_once(|| {
        // Both are valid TrueType files shipped by the crate; a failure would only mean text
        // is missing, which drawing then reports as an error.
        let _ = plotters::style::register_font(FONT, FontStyle::Normal, dejavu::sans::regular());
        let _ = plotters::style::register_font(FONT, FontStyle::Bold, dejavu::sans::bold());
    });
}

fn font(size: u32) -> TextStyle<'static> {
    (FONT, size).into_font().color(&BLACK)
}

/// Draws with `draw` on a white `WIDTH` x `HEIGHT` canvas and writes it to `path` as PNG.
fn render(path: &Path, draw: impl FnOnce(&DrawingArea<BitMapBackend<'_>, Shift>) -> Drawn) -> Result<(), PlotError> {
    register_fonts();
    let mut buffer = vec![255u8; (WIDTH * HEIGHT * 3) as usize];
    {
        let root = BitMapBackend::with_buffer(&mut buffer, (WIDTH, HEIGHT)).into_drawing_area();
        root.fill(&WHITE).map_err(|e| PlotError(format!("drawing: {e}")))?;
        draw(&root).map_err(|e| PlotError(format!("drawing: {e}")))?;
        root.present().map_err(|e| PlotError(format!("drawing: {e}")))?;
    }
    write_png(path, WIDTH, HEIGHT, &buffer).map_err(|e| PlotError(format!("{}: {e}", path.display())))
}

/// Writes 8-bit RGB pixels as a PNG file.
pub fn write_png(path: &Path, width: u32, height: u32, rgb: &[u8]) -> Result<(), Box<dyn Error>> {
    let file = BufWriter::new(File::create(path)?);
    let mut encoder = png::Encoder::new(file, width, height);
    encoder.set_color(png::ColorType::Rgb);
    encoder.set_depth(png::BitDepth::Eight);
    let mut writer = encoder.write_header()?;
    writer.write_image_data(rgb)?;
    writer.finish()?;
    Ok(())
}

/// The width and height a PNG file declares (its signature and IHDR chunk), `None` if the
/// bytes are not a PNG.
pub fn png_size(bytes: &[u8]) -> Option<(u32, u32)> {
    const SIGNATURE: &[u8] = b"\x89PNG\r\n\x1a\n";
    if bytes.len() < 24 || &bytes[..8] != SIGNATURE || &bytes[12..16] != b"IHDR" {
        return None;
    }
    let be = |b: &[u8]| u32::from_be_bytes([b[0], b[1], b[2], b[3]]);
    Some((be(&bytes[16..20]), be(&bytes[20..24])))
}

// ---------------------------------------------------------------------------------------------
// Heatmap

/// What [`heatmap_png`] draws.
#[derive(Debug, Clone)]
pub struct HeatmapPicture<'a> {
    pub title: String,
    pub grid: Grid,
    /// One value in [0, 1] per bin (`None`: masked), flat `a * ny + b`.
    pub values: &'a [Option<f64>],
    /// Walls as `[rows, cols]` row-major flags, with the maze's cell (0, 0) first.
    pub walls: Option<(usize, usize, &'a [bool])>,
    pub goal: Option<(f64, f64)>,
    /// The smoothed maximum.
    pub argmax: Option<(f64, f64)>,
    /// Label of the colour bar.
    pub scale_label: String,
}

/// A five-pointed star of outer radius `r` pixels, centred on (0, 0), pointing up.
fn star(r: f64) -> Vec<(i32, i32)> {
    (0..10)
        .map(|k| {
            let radius = if k % 2 == 0 { r } else { r * 0.45 };
            let angle = std::f64::consts::PI * (k as f64 / 5.0 - 0.5);
            ((radius * angle.cos()).round() as i32, (radius * angle.sin()).round() as i32)
        })
        .collect()
}

/// Draws the maze heatmap: columns (y) to the right, rows (x) downwards, so the picture reads
/// like D4RL's layout strings; a colour bar on the right; walls dark; masked bins light grey;
/// the goal a red star; the smoothed maximum a white cross in a black ring.
pub fn heatmap_png(path: &Path, picture: &HeatmapPicture<'_>) -> Result<(), PlotError> {
    render(path, |root| draw_heatmap(root, picture))
}

fn draw_heatmap(root: &DrawingArea<BitMapBackend<'_>, Shift>, p: &HeatmapPicture<'_>) -> Drawn {
    let area = root.titled(&p.title, font(TITLE_SIZE))?;
    let (w, h) = area.dim_in_pixel();
    let bar_width = 120;
    let (main, bar) = area.split_horizontally(w.saturating_sub(bar_width));
    let g = &p.grid;
    let (x0, y0) = g.origin();
    let (x1, y1) = (x0 + g.rows as f64, y0 + g.cols as f64);
    // Square cells: the plot area's free space goes to the margins.
    let (label_x, label_y, margin) = (50u32, 60u32, 12u32);
    let avail_w = f64::from(main.dim_in_pixel().0.saturating_sub(label_y + 2 * margin));
    let avail_h = f64::from(h.saturating_sub(label_x + 2 * margin));
    let cell = (avail_w / g.cols.max(1) as f64).min(avail_h / g.rows.max(1) as f64);
    let extra_w = ((avail_w - cell * g.cols as f64) / 2.0).max(0.0) as u32;
    let extra_h = ((avail_h - cell * g.rows as f64) / 2.0).max(0.0) as u32;
    let mut chart = ChartBuilder::on(&main)
        .margin_left(margin + extra_w)
        .margin_right(margin + extra_w)
        .margin_top(margin + extra_h)
        .margin_bottom(margin + extra_h)
        .x_label_area_size(label_x)
        .y_label_area_size(label_y)
        // Vertical axis: -x, so that row 0 is at the top.
        .build_cartesian_2d(y0..y1, -x1..-x0)?;
    let ticks = |n: usize| (n + 1).min(13);
    chart
        .configure_mesh()
        .disable_mesh()
        .set_all_tick_mark_size(6)
        .x_labels(ticks(g.cols))
        .y_labels(ticks(g.rows))
        .x_label_formatter(&|v| format_tick(*v))
        .y_label_formatter(&|v| format_tick(-*v))
        .x_desc("y (maze column)")
        .y_desc("x (maze row)")
        .label_style(font(TICK_SIZE))
        .axis_desc_style(font(LABEL_SIZE))
        .draw()?;
    chart.plotting_area().fill(&MASKED)?;
    let (_, ny) = g.shape();
    let s = g.bin_size();
    chart.draw_series(p.values.iter().enumerate().filter_map(|(k, v)| {
        let v = (*v)?;
        let (a, b) = ((k / ny) as f64, (k % ny) as f64);
        let (xa, yb) = (x0 + a * s, y0 + b * s);
        Some(Rectangle::new([(yb, -xa), (yb + s, -(xa + s))], ViridisRGB::get_color(v.clamp(0.0, 1.0)).filled()))
    }))?;
    if let Some((rows, cols, walls)) = p.walls {
        chart.draw_series((0..rows * cols).filter(|&k| walls.get(k).copied().unwrap_or(false)).map(|k| {
            let (i, j) = ((k / cols) as f64, (k % cols) as f64);
            Rectangle::new([(j - 0.5, -(i - 0.5)), (j + 0.5, -(i + 0.5))], WALL.filled())
        }))?;
    }
    if let Some((gx, gy)) = p.goal {
        chart
            .draw_series(std::iter::once(
                EmptyElement::at((gy, -gx))
                    + Polygon::new(star(13.0), RED.filled())
                    + PathElement::new(
                        {
                            let mut outline = star(13.0);
                            outline.push(outline[0]);
                            outline
                        },
                        BLACK.stroke_width(1),
                    ),
            ))?
            .label("goal")
            .legend(|(x, y)| {
                let points = star(7.0).into_iter().map(|(dx, dy)| (x + 8 + dx, y + dy)).collect::<Vec<_>>();
                Polygon::new(points, RED.filled())
            });
    }
    if let Some((mx, my)) = p.argmax {
        chart
            .draw_series(std::iter::once(
                EmptyElement::at((my, -mx))
                    + Circle::new((0, 0), 10, BLACK.stroke_width(3))
                    + Cross::new((0, 0), 6, WHITE.stroke_width(3)),
            ))?
            .label("smoothed maximum")
            .legend(|(x, y)| {
                EmptyElement::at((x + 8, y))
                    + Circle::new((0, 0), 6, BLACK.stroke_width(2))
                    + Cross::new((0, 0), 3, BLACK.stroke_width(2))
            });
    }
    if p.goal.is_some() || p.argmax.is_some() {
        chart
            .configure_series_labels()
            .position(SeriesLabelPosition::LowerRight)
            .background_style(WHITE.mix(0.85))
            .border_style(BLACK)
            .label_font(font(TICK_SIZE))
            .draw()?;
    }

    // The colour bar, as tall as the heatmap's plotting area.
    let mut scale = ChartBuilder::on(&bar)
        .margin_top(margin + extra_h)
        .margin_bottom(margin + extra_h)
        .margin_left(8)
        .margin_right(10)
        .x_label_area_size(label_x)
        .right_y_label_area_size(70)
        .build_cartesian_2d(0.0..1.0, 0.0..1.0)?;
    scale
        .configure_mesh()
        .disable_mesh()
        .disable_x_axis()
        .set_all_tick_mark_size(6)
        .y_labels(6)
        .y_label_formatter(&|v| format!("{v:.1}"))
        .y_desc(p.scale_label.as_str())
        .label_style(font(TICK_SIZE))
        .axis_desc_style(font(LABEL_SIZE))
        .draw()?;
    let steps = 200;
    scale.draw_series((0..steps).map(|i| {
        let (lo, hi) = (i as f64 / steps as f64, (i + 1) as f64 / steps as f64);
        Rectangle::new([(0.0, lo), (1.0, hi)], ViridisRGB::get_color(0.5 * (lo + hi)).filled())
    }))?;
    Ok(())
}

/// A cell index for a tick: integers as such, anything else with one decimal.
fn format_tick(v: f64) -> String {
    let r = v.round();
    if (v - r).abs() < 1e-9 { format!("{}", r as i64) } else { format!("{v:.1}") }
}

// ---------------------------------------------------------------------------------------------
// Loss curves

/// One line of a loss plot: `(step, value)` points.
#[derive(Debug, Clone)]
pub struct Series {
    pub name: String,
    pub points: Vec<(f64, f64)>,
}

/// Whether a loss plot should use a log scale: every value positive and the largest over 100
/// times the smallest.
pub fn wants_log_scale(series: &[Series]) -> bool {
    let values = || series.iter().flat_map(|s| s.points.iter().map(|p| p.1)).filter(|v| v.is_finite());
    let (lo, hi) = values().fold((f64::INFINITY, f64::NEG_INFINITY), |(lo, hi), v| (lo.min(v), hi.max(v)));
    lo > 0.0 && hi / lo > 100.0
}

/// A line plot of `series` against the step, log-scale y when `log`.
/// Each series as a line (with markers when short) and the legend, on a chart whose y axis is
/// linear or logarithmic (the one part the two loss-plot variants share).
fn draw_series_with_legend<'a, Y>(
    chart: &mut ChartContext<'a, BitMapBackend<'a>, Cartesian2d<plotters::coord::types::RangedCoordf64, Y>>,
    series: &[Series],
    finite: impl Fn(&&(f64, f64)) -> bool,
) -> Drawn
where
    Y: Ranged<ValueType = f64>,
{
    for (i, s) in series.iter().enumerate() {
        let color = SERIES[i % SERIES.len()];
        let points: Vec<(f64, f64)> = s.points.iter().filter(&finite).copied().collect();
        chart
            .draw_series(LineSeries::new(points.clone(), color.stroke_width(2)))?
            .label(s.name.as_str())
            .legend(move |(x, y)| PathElement::new(vec![(x, y), (x + 20, y)], color.stroke_width(2)));
        if points.len() <= 60 {
            chart.draw_series(points.iter().map(|&p| Circle::new(p, 3, color.filled())))?;
        }
    }
    chart
        .configure_series_labels()
        .background_style(WHITE.mix(0.85))
        .border_style(BLACK)
        .label_font(font(TICK_SIZE))
        .draw()?;
    Ok(())
}

pub fn loss_png(path: &Path, title: &str, y_label: &str, series: &[Series], log: bool) -> Result<(), PlotError> {
    render(path, |root| draw_lines(root, title, y_label, series, log))
}

fn draw_lines(
    root: &DrawingArea<BitMapBackend<'_>, Shift>,
    title: &str,
    y_label: &str,
    series: &[Series],
    log: bool,
) -> Drawn {
    let finite = |p: &&(f64, f64)| p.0.is_finite() && p.1.is_finite() && (!log || p.1 > 0.0);
    let all: Vec<(f64, f64)> = series.iter().flat_map(|s| s.points.iter().filter(finite).copied()).collect();
    let (mut x_lo, mut x_hi) = bounds(all.iter().map(|p| p.0));
    let (mut y_lo, mut y_hi) = bounds(all.iter().map(|p| p.1));
    if x_hi <= x_lo {
        (x_lo, x_hi) = (x_lo - 1.0, x_hi + 1.0);
    }
    if log {
        // Whole decades around the data, so that every decade has a labelled tick.
        (y_lo, y_hi) = (10f64.powf(y_lo.log10().floor()), 10f64.powf(y_hi.log10().ceil()));
        if y_hi <= y_lo {
            y_hi = y_lo * 10.0;
        }
    } else {
        let pad = if y_hi > y_lo { 0.05 * (y_hi - y_lo) } else { 1.0 };
        (y_lo, y_hi) = (y_lo - pad, y_hi + pad);
    }
    let mut builder = ChartBuilder::on(root);
    builder.caption(title, font(TITLE_SIZE)).margin(20).x_label_area_size(55).y_label_area_size(85);
    let x_label = "training step";
    if log {
        let mut chart = builder.build_cartesian_2d(x_lo..x_hi, (y_lo..y_hi).log_scale())?;
        chart
            .configure_mesh()
            .x_desc(x_label)
            .y_desc(format!("{y_label} (log scale)"))
            .y_label_formatter(&|v| format!("{v:.0e}"))
            .x_label_formatter(&|v| format_count(*v))
            .label_style(font(TICK_SIZE))
            .axis_desc_style(font(LABEL_SIZE))
            .light_line_style(RGBColor(235, 235, 235))
            .draw()?;
        draw_series_with_legend(&mut chart, series, finite)?;
    } else {
        let mut chart = builder.build_cartesian_2d(x_lo..x_hi, y_lo..y_hi)?;
        chart
            .configure_mesh()
            .x_desc(x_label)
            .y_desc(y_label)
            .y_label_formatter(&|v| format_value(*v))
            .x_label_formatter(&|v| format_count(*v))
            .label_style(font(TICK_SIZE))
            .axis_desc_style(font(LABEL_SIZE))
            .light_line_style(RGBColor(235, 235, 235))
            .draw()?;
        draw_series_with_legend(&mut chart, series, finite)?;
    }
    Ok(())
}

/// (min, max) of finite values; (0, 1) for none.
fn bounds(values: impl Iterator<Item = f64>) -> (f64, f64) {
    let (lo, hi) =
        values.filter(|v| v.is_finite()).fold((f64::INFINITY, f64::NEG_INFINITY), |(lo, hi), v| (lo.min(v), hi.max(v)));
    if lo <= hi { (lo, hi) } else { (0.0, 1.0) }
}

/// A step count tick: `1500`, `12k`, `1.5M`.
fn format_count(v: f64) -> String {
    let a = v.abs();
    if a >= 1e6 {
        format!("{}M", trim(v / 1e6))
    } else if a >= 1e4 {
        format!("{}k", trim(v / 1e3))
    } else {
        trim(v)
    }
}

fn trim(v: f64) -> String {
    let text = format!("{v:.2}");
    text.trim_end_matches('0').trim_end_matches('.').to_owned()
}

/// A value tick: three significant digits.
fn format_value(v: f64) -> String {
    let a = v.abs();
    if a != 0.0 && !(1e-3..1e5).contains(&a) {
        format!("{v:.2e}")
    } else {
        trim(if a < 1.0 { v } else { (v * 100.0).round() / 100.0 })
    }
}

// ---------------------------------------------------------------------------------------------
// Histograms

/// Overlaid histograms of `groups` (name, values) on shared bins, each normalised to unit
/// area (a density) so that groups of different sizes compare.
pub fn histogram_png(
    path: &Path,
    title: &str,
    x_label: &str,
    groups: &[(String, Vec<f64>)],
    bins: usize,
) -> Result<(), PlotError> {
    render(path, |root| draw_histogram(root, title, x_label, groups, bins.max(1)))
}

/// Densities of `values` on `bins` equal bins over [lo, hi] (values outside are left out).
pub fn densities(values: &[f64], lo: f64, hi: f64, bins: usize) -> Vec<f64> {
    let width = (hi - lo) / bins as f64;
    let mut counts = vec![0usize; bins];
    for &v in values {
        if v.is_finite() && v >= lo && v <= hi && width > 0.0 {
            counts[(((v - lo) / width) as usize).min(bins - 1)] += 1;
        }
    }
    let total = counts.iter().sum::<usize>().max(1) as f64;
    counts.into_iter().map(|c| c as f64 / (total * width.max(f64::MIN_POSITIVE))).collect()
}

fn draw_histogram(
    root: &DrawingArea<BitMapBackend<'_>, Shift>,
    title: &str,
    x_label: &str,
    groups: &[(String, Vec<f64>)],
    bins: usize,
) -> Drawn {
    let (mut lo, mut hi) = bounds(groups.iter().flat_map(|(_, v)| v.iter().copied()));
    if hi <= lo {
        (lo, hi) = (lo - 0.5, hi + 0.5);
    }
    let width = (hi - lo) / bins as f64;
    let dens: Vec<Vec<f64>> = groups.iter().map(|(_, v)| densities(v, lo, hi, bins)).collect();
    let top = dens.iter().flatten().copied().fold(0.0, f64::max).max(f64::MIN_POSITIVE) * 1.08;
    let mut chart = ChartBuilder::on(root)
        .caption(title, font(TITLE_SIZE))
        .margin(20)
        .x_label_area_size(55)
        .y_label_area_size(85)
        .build_cartesian_2d(lo..hi, 0.0..top)?;
    chart
        .configure_mesh()
        .x_desc(x_label)
        .y_desc("density")
        .x_label_formatter(&|v| format_value(*v))
        .y_label_formatter(&|v| format_value(*v))
        .label_style(font(TICK_SIZE))
        .axis_desc_style(font(LABEL_SIZE))
        .light_line_style(RGBColor(235, 235, 235))
        .draw()?;
    for (i, ((name, values), d)) in groups.iter().zip(&dens).enumerate() {
        let color = SERIES[i % SERIES.len()];
        chart.draw_series(d.iter().enumerate().map(|(k, &v)| {
            let x = lo + k as f64 * width;
            Rectangle::new([(x, 0.0), (x + width, v)], color.mix(0.35).filled())
        }))?;
        // The outline as a step line, so overlapping bars stay readable.
        let mut outline = vec![(lo, 0.0)];
        for (k, &v) in d.iter().enumerate() {
            let x = lo + k as f64 * width;
            outline.push((x, v));
            outline.push((x + width, v));
        }
        outline.push((hi, 0.0));
        chart
            .draw_series(LineSeries::new(outline, color.stroke_width(2)))?
            .label(format!("{name} (n = {})", values.len()))
            .legend(move |(x, y)| Rectangle::new([(x, y - 6), (x + 20, y + 6)], color.mix(0.6).filled()));
    }
    chart
        .configure_series_labels()
        .position(SeriesLabelPosition::UpperRight)
        .background_style(WHITE.mix(0.85))
        .border_style(BLACK)
        .label_font(font(TICK_SIZE))
        .draw()?;
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;

    fn decode(path: &Path) -> (png::OutputInfo, Vec<u8>) {
        let decoder = png::Decoder::new(std::io::BufReader::new(File::open(path).expect("open")));
        let mut reader = decoder.read_info().expect("png header");
        let mut pixels = vec![0; reader.output_buffer_size().expect("size")];
        let info = reader.next_frame(&mut pixels).expect("png frame");
        pixels.truncate(info.buffer_size());
        (info, pixels)
    }

    /// Pixels that are neither white nor grey (text and lines are dark; data is coloured).
    fn dark_pixels(pixels: &[u8], rows: std::ops::Range<usize>, width: usize) -> usize {
        rows.flat_map(|r| pixels[r * width * 3..(r + 1) * width * 3].chunks(3))
            .filter(|p| p.iter().all(|&c| c < 100))
            .count()
    }

    #[test]
    fn png_headers_are_read() {
        let dir = tempfile::tempdir().expect("tmp");
        let path = dir.path().join("x.png");
        write_png(&path, 3, 2, &[0; 18]).expect("write");
        let bytes = std::fs::read(&path).expect("read");
        assert_eq!(png_size(&bytes), Some((3, 2)));
        assert_eq!(png_size(b"not a png at all, not at all"), None);
    }

    #[test]
    fn a_heatmap_is_a_png_with_text_walls_goal_and_colour_bar() {
        let dir = tempfile::tempdir().expect("tmp");
        let path = dir.path().join("heatmap.png");
        let grid = Grid::of_maze(5, 5, 10);
        let values: Vec<Option<f64>> = (0..grid.len())
            .map(|k| {
                let (x, y) = grid.bin_centre(k);
                (x > 0.5 && x < 3.5)
                    .then(|| (1.0 - ((x - 2.0).powi(2) + (y - 3.0).powi(2)).sqrt() / 4.0).clamp(0.0, 1.0))
            })
            .collect();
        let mut walls = vec![false; 25];
        for k in 0..5 {
            walls[k] = true;
            walls[20 + k] = true;
            walls[5 * k] = true;
            walls[5 * k + 4] = true;
        }
        let picture = HeatmapPicture {
            title: "reward heatmap".into(),
            grid,
            values: &values,
            walls: Some((5, 5, &walls)),
            goal: Some((2.0, 3.0)),
            argmax: Some((2.05, 2.95)),
            scale_label: "scaled reward".into(),
        };
        heatmap_png(&path, &picture).expect("heatmap");
        let (info, pixels) = decode(&path);
        assert_eq!((info.width, info.height, info.color_type), (WIDTH, HEIGHT, png::ColorType::Rgb));
        // The title is text: dark pixels in the top band.
        assert!(dark_pixels(&pixels, 0..35, WIDTH as usize) > 100, "no title drawn");
        // Red (the goal star) is present.
        assert!(pixels.chunks(3).any(|p| p[0] > 200 && p[1] < 40 && p[2] < 40), "no goal star");
        // Viridis yellow (the colour bar's top) is present.
        assert!(pixels.chunks(3).any(|p| p[0] > 240 && p[1] > 220 && p[2] < 60), "no colour bar");
    }

    #[test]
    fn loss_curves_and_histograms_are_pngs() {
        let dir = tempfile::tempdir().expect("tmp");
        let series = vec![
            Series { name: "loss".into(), points: (1..=50).map(|s| (f64::from(s), 10.0 / f64::from(s * s))).collect() },
            Series { name: "eval loss".into(), points: vec![(10.0, 0.2), (50.0, 0.01)] },
        ];
        assert!(wants_log_scale(&series));
        assert!(!wants_log_scale(&[Series { name: "l".into(), points: vec![(0.0, 1.0), (1.0, 0.5)] }]));
        assert!(!wants_log_scale(&[Series { name: "l".into(), points: vec![(0.0, -1.0), (1.0, 500.0)] }]));
        for log in [true, false] {
            let path = dir.path().join(format!("loss-{log}.png"));
            loss_png(&path, "job j (reward)", "loss", &series, log).expect("loss");
            let (info, pixels) = decode(&path);
            assert_eq!((info.width, info.height), (WIDTH, HEIGHT));
            assert!(dark_pixels(&pixels, 0..60, WIDTH as usize) > 100, "no title drawn");
        }
        let path = dir.path().join("hist.png");
        let groups = vec![
            ("base".to_owned(), (0..500).map(|i| f64::from(i % 50) / 10.0).collect()),
            ("expert".to_owned(), (0..300).map(|i| 3.0 + f64::from(i % 30) / 10.0).collect()),
        ];
        histogram_png(&path, "rewards", "reward rho", &groups, 30).expect("histogram");
        let bytes = std::fs::read(&path).expect("read");
        assert_eq!(png_size(&bytes), Some((WIDTH, HEIGHT)));
        // Densities integrate to one.
        let d = densities(&[0.0, 0.5, 1.0, 1.0], 0.0, 1.0, 4);
        assert!((d.iter().sum::<f64>() * 0.25 - 1.0).abs() < 1e-12);
        assert_eq!(d, vec![1.0, 0.0, 1.0, 2.0]);
    }
}
