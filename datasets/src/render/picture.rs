//! Pictures of motion a person can look at: an animated GIF of the skeleton and a PNG contact
//! sheet of evenly spaced frames. A fixed 3/4 camera (orthographic) over a ground grid; left
//! limbs blue, right limbs red, a floor shadow, and feet in contact with the ground marked green.
//! Drawing is our own (thick lines as stamped discs) into a small fixed palette.

use std::path::Path;

use ndarray::Array3;

use crate::error::{Error, Result};
use crate::formats::motion_file::{MotionFile, write_atomic_bytes};
use crate::rotation::{Vec3, cross, dot};

/// How to draw.
#[derive(Debug, Clone)]
#[non_exhaustive]
pub struct RenderOptions {
    /// Image (GIF) or tile (contact sheet) width, pixels. Default: 360.
    pub width: u32,
    /// Image or tile height, pixels. Default: 360.
    pub height: u32,
    /// Highest GIF frame rate; frames are skipped above it. Default: 15.
    pub max_fps: f32,
    /// Camera azimuth from the front (+z) toward the dancer's left (+x), degrees. Default: 35.
    pub azimuth_deg: f32,
    /// Camera elevation above the floor plane, degrees. Default: 20.
    pub elevation_deg: f32,
    /// Contact-sheet columns. Default: 4.
    pub sheet_columns: usize,
    /// Contact-sheet rows. Default: 3.
    pub sheet_rows: usize,
    /// A foot joint slower than this is in contact, m/s (EDGE vis.py: 0.01 m per frame at 30 fps).
    /// Default: 0.3.
    pub contact_speed: f32,
}

impl Default for RenderOptions {
    fn default() -> Self {
        RenderOptions {
            width: 360,
            height: 360,
            max_fps: 15.0,
            azimuth_deg: 35.0,
            elevation_deg: 20.0,
            sheet_columns: 4,
            sheet_rows: 3,
            contact_speed: 0.3,
        }
    }
}

const BG: u8 = 0;
const GRID: u8 = 1;
const SHADOW: u8 = 2;
const CENTER: u8 = 3;
const LEFT: u8 = 4;
const RIGHT: u8 = 5;
const CONTACT: u8 = 6;
const JOINT: u8 = 7;
const TEXT: u8 = 8;
const BORDER: u8 = 9;
const PALETTE: [[u8; 3]; 10] = [
    [250, 250, 246],
    [205, 205, 198],
    [196, 196, 190],
    [70, 70, 80],
    [40, 105, 215],
    [215, 55, 45],
    [20, 165, 60],
    [35, 35, 40],
    [90, 90, 90],
    [170, 170, 170],
];

/// An indexed-colour canvas.
struct Canvas {
    w: usize,
    h: usize,
    px: Vec<u8>,
}

impl Canvas {
    fn new(w: usize, h: usize) -> Self {
        Canvas {
            w,
            h,
            px: vec![BG; w * h],
        }
    }

    fn disc(&mut self, cx: f32, cy: f32, r: f32, c: u8) {
        let (x0, x1) = ((cx - r).floor() as i64, (cx + r).ceil() as i64);
        let (y0, y1) = ((cy - r).floor() as i64, (cy + r).ceil() as i64);
        for y in y0.max(0)..=y1.min(self.h as i64 - 1) {
            for x in x0.max(0)..=x1.min(self.w as i64 - 1) {
                let (dx, dy) = (x as f32 - cx, y as f32 - cy);
                if dx * dx + dy * dy <= r * r {
                    self.px[y as usize * self.w + x as usize] = c;
                }
            }
        }
    }

    fn line(&mut self, a: [f32; 2], b: [f32; 2], r: f32, c: u8) {
        let len = ((b[0] - a[0]).powi(2) + (b[1] - a[1]).powi(2)).sqrt();
        let steps = (len / (r * 0.5).max(0.5)).ceil().max(1.0) as usize;
        // Lines far outside the canvas (bad data) are skipped rather than stamped for ever.
        if steps > 100_000 {
            return;
        }
        for i in 0..=steps {
            let t = i as f32 / steps as f32;
            self.disc(a[0] + (b[0] - a[0]) * t, a[1] + (b[1] - a[1]) * t, r, c);
        }
    }

    fn rect(&mut self, x0: usize, y0: usize, x1: usize, y1: usize, c: u8) {
        for x in x0..x1.min(self.w) {
            for y in [y0, y1.saturating_sub(1)] {
                if y < self.h {
                    self.px[y * self.w + x] = c;
                }
            }
        }
        for y in y0..y1.min(self.h) {
            for x in [x0, x1.saturating_sub(1)] {
                if x < self.w {
                    self.px[y * self.w + x] = c;
                }
            }
        }
    }

    /// Tiny 3×5 bitmap text (digits, '.', 's', ':', '/'), scaled by `scale`.
    fn text(&mut self, x: usize, y: usize, s: &str, scale: usize, c: u8) {
        let mut cx = x;
        for ch in s.chars() {
            let glyph: u16 = match ch {
                '0' => 0b111_101_101_101_111,
                '1' => 0b010_110_010_010_111,
                '2' => 0b111_001_111_100_111,
                '3' => 0b111_001_111_001_111,
                '4' => 0b101_101_111_001_001,
                '5' => 0b111_100_111_001_111,
                '6' => 0b111_100_111_101_111,
                '7' => 0b111_001_010_010_010,
                '8' => 0b111_101_111_101_111,
                '9' => 0b111_101_111_001_111,
                '.' => 0b000_000_000_000_010,
                's' => 0b000_011_110_011_110,
                ':' => 0b000_010_000_010_000,
                '/' => 0b001_001_010_100_100,
                _ => 0,
            };
            for row in 0..5 {
                for col in 0..3 {
                    if glyph >> (14 - (row * 3 + col)) & 1 == 1 {
                        for dy in 0..scale {
                            for dx in 0..scale {
                                let (px, py) = (cx + col * scale + dx, y + row * scale + dy);
                                if px < self.w && py < self.h {
                                    self.px[py * self.w + px] = c;
                                }
                            }
                        }
                    }
                }
            }
            cx += 4 * scale;
        }
    }
}

/// Orthographic 3/4 camera fitted to the whole take.
struct Camera {
    right: Vec3,
    up: Vec3,
    fwd: Vec3,
    scale: f32,
    cu: f32,
    cv: f32,
    w: f32,
    h: f32,
}

impl Camera {
    fn fit(points: &[Vec3], w: usize, h: usize, opts: &RenderOptions) -> Self {
        let (az, el) = (
            opts.azimuth_deg.to_radians(),
            opts.elevation_deg.to_radians(),
        );
        let eye = [az.sin() * el.cos(), el.sin(), az.cos() * el.cos()];
        let fwd = [-eye[0], -eye[1], -eye[2]];
        let r = cross(fwd, [0.0, 1.0, 0.0]);
        let rn = dot(r, r).sqrt().max(1e-6);
        let right = [r[0] / rn, r[1] / rn, r[2] / rn];
        let up = cross(right, fwd);
        let (mut umin, mut umax, mut vmin, mut vmax) = (f32::MAX, f32::MIN, f32::MAX, f32::MIN);
        for p in points {
            let (u, v) = (dot(*p, right), dot(*p, up));
            umin = umin.min(u);
            umax = umax.max(u);
            vmin = vmin.min(v);
            vmax = vmax.max(v);
        }
        if umin > umax {
            (umin, umax, vmin, vmax) = (-1.0, 1.0, -1.0, 1.0);
        }
        // 8 % margin; at least a 1 m window so a lone point is not blown up.
        let span_u = (umax - umin).max(1.0) * 1.08;
        let span_v = (vmax - vmin).max(1.0) * 1.08;
        let scale = (w as f32 / span_u).min(h as f32 / span_v);
        Camera {
            right,
            up,
            fwd,
            scale,
            cu: (umin + umax) / 2.0,
            cv: (vmin + vmax) / 2.0,
            w: w as f32,
            h: h as f32,
        }
    }

    fn project(&self, p: Vec3) -> [f32; 2] {
        let u = dot(p, self.right) - self.cu;
        let v = dot(p, self.up) - self.cv;
        [self.w / 2.0 + u * self.scale, self.h / 2.0 - v * self.scale]
    }

    fn depth(&self, p: Vec3) -> f32 {
        dot(p, self.fwd)
    }
}

/// Precomputed scene: floor height, grid extent, contacts.
struct Scene<'a> {
    m: &'a MotionFile,
    floor: f32,
    grid: (f32, f32, f32, f32),
    contact: Vec<Vec<bool>>,
    feet: Vec<usize>,
}

fn joint(j: &Array3<f32>, t: usize, k: usize) -> Vec3 {
    [j[[t, k, 0]], j[[t, k, 1]], j[[t, k, 2]]]
}

impl<'a> Scene<'a> {
    fn new(m: &'a MotionFile, path: &Path, opts: &RenderOptions) -> Result<Self> {
        m.validate(path)?;
        let j = &m.joints;
        let (t, n) = (j.shape()[0], j.shape()[1]);
        // Widest extent along one axis; f64 because the span of finite f32 extremes can overflow.
        let span = (0..3)
            .map(|a| {
                let axis = j.index_axis(ndarray::Axis(2), a);
                let (lo, hi) = axis
                    .iter()
                    .fold((f32::MAX, f32::MIN), |(lo, hi), v| (lo.min(*v), hi.max(*v)));
                f64::from(hi) - f64::from(lo)
            })
            .fold(0.0, f64::max);
        if span > MAX_SPAN_M {
            return Err(Error::invalid(
                path,
                format!(
                    "the motion spans {span:.3e} m (more than {MAX_SPAN_M} m): \
                     not a body in metres, so nothing sensible to draw"
                ),
            ));
        }
        let feet = m.skeleton.foot_joints();
        let floor = if feet.is_empty() {
            j.iter()
                .skip(1)
                .step_by(3)
                .copied()
                .fold(f32::MAX, f32::min)
        } else {
            (0..t)
                .flat_map(|f| feet.iter().map(move |k| (f, *k)))
                .map(|(f, k)| j[[f, k, 1]])
                .fold(f32::MAX, f32::min)
        };
        let (mut x0, mut x1, mut z0, mut z1) = (f32::MAX, f32::MIN, f32::MAX, f32::MIN);
        for f in 0..t {
            for k in 0..n {
                x0 = x0.min(j[[f, k, 0]]);
                x1 = x1.max(j[[f, k, 0]]);
                z0 = z0.min(j[[f, k, 2]]);
                z1 = z1.max(j[[f, k, 2]]);
            }
        }
        // Grid on 0.5 m lines just covering the motion (a wider grid shrinks the dancer).
        let snap = |v: f32, up: bool| {
            if up {
                (v / GRID_STEP_M).ceil() * GRID_STEP_M
            } else {
                (v / GRID_STEP_M).floor() * GRID_STEP_M
            }
        };
        let grid = (
            snap(x0, false),
            snap(x1, true),
            snap(z0, false),
            snap(z1, true),
        );
        let limit = opts.contact_speed / m.fps;
        let contact = (0..t)
            .map(|f| {
                let g = if f + 1 < t {
                    f + 1
                } else {
                    f.saturating_sub(1)
                };
                feet.iter()
                    .map(|k| {
                        let (a, b) = (joint(j, f, *k), joint(j, g, *k));
                        let d =
                            ((a[0] - b[0]).powi(2) + (a[1] - b[1]).powi(2) + (a[2] - b[2]).powi(2))
                                .sqrt();
                        // Also near the floor: a foot held still in the air is not a contact.
                        t > 1 && d < limit && a[1] - floor < 0.12
                    })
                    .collect()
            })
            .collect();
        Ok(Scene {
            m,
            floor,
            grid,
            contact,
            feet,
        })
    }

    fn camera(&self, w: usize, h: usize, opts: &RenderOptions) -> Camera {
        let j = &self.m.joints;
        let mut pts = Vec::new();
        let step = (j.shape()[0] / 200).max(1);
        for f in (0..j.shape()[0]).step_by(step) {
            for k in 0..j.shape()[1] {
                pts.push(joint(j, f, k));
            }
        }
        let (x0, x1, z0, z1) = self.grid;
        for (x, z) in [(x0, z0), (x0, z1), (x1, z0), (x1, z1)] {
            pts.push([x, self.floor, z]);
        }
        Camera::fit(&pts, w, h, opts)
    }

    fn draw(&self, c: &mut Canvas, cam: &Camera, t: usize) {
        let (x0, x1, z0, z1) = self.grid;
        let thin = (c.w.min(c.h) as f32 / 360.0).max(0.5);
        // Counted lines, not `x += 0.5` until past the end: in f32 that addition stops
        // advancing once x is large (≈1.7e7), and the loop would never end.
        for i in 0..=grid_lines(x0, x1) {
            let x = x0 + GRID_STEP_M * i as f32;
            c.line(
                cam.project([x, self.floor, z0]),
                cam.project([x, self.floor, z1]),
                0.5 * thin,
                GRID,
            );
        }
        for i in 0..=grid_lines(z0, z1) {
            let z = z0 + GRID_STEP_M * i as f32;
            c.line(
                cam.project([x0, self.floor, z]),
                cam.project([x1, self.floor, z]),
                0.5 * thin,
                GRID,
            );
        }
        let j = &self.m.joints;
        let parents = self.m.skeleton.parents();
        // Shadow: the skeleton flattened onto the floor.
        for (k, p) in parents.iter().enumerate() {
            if *p >= 0 {
                let (mut a, mut b) = (joint(j, t, k), joint(j, t, *p as usize));
                a[1] = self.floor;
                b[1] = self.floor;
                c.line(cam.project(a), cam.project(b), 2.5 * thin, SHADOW);
            }
        }
        // Bones far to near so the near limbs stay on top.
        let mut bones: Vec<(f32, usize, usize)> = parents
            .iter()
            .enumerate()
            .filter(|(_, p)| **p >= 0)
            .map(|(k, p)| {
                let d = cam.depth(joint(j, t, k)) + cam.depth(joint(j, t, *p as usize));
                (d, k, *p as usize)
            })
            .collect();
        bones.sort_by(|a, b| b.0.total_cmp(&a.0));
        for (_, k, p) in bones {
            let colour = if self.m.skeleton.is_left(k) {
                LEFT
            } else if self.m.skeleton.is_right(k) {
                RIGHT
            } else {
                CENTER
            };
            let (a, b) = (cam.project(joint(j, t, k)), cam.project(joint(j, t, p)));
            c.line(a, b, 3.0 * thin, colour);
            c.disc(a[0], a[1], 2.2 * thin, JOINT);
        }
        // Head: a larger disc on the topmost leaf of the spine chain (joint named head, else 15).
        let names = self.m.skeleton.joint_names();
        if let Some(h) = names
            .iter()
            .position(|n| n.to_ascii_lowercase().contains("head"))
        {
            let p = cam.project(joint(j, t, h));
            c.disc(p[0], p[1], 7.0 * thin, CENTER);
        }
        for (i, k) in self.feet.iter().enumerate() {
            if self.contact[t][i] {
                let p = cam.project(joint(j, t, *k));
                c.disc(p[0], p[1], 5.0 * thin, CONTACT);
            }
        }
    }
}

/// Spacing of the floor grid, metres.
const GRID_STEP_M: f32 = 0.5;
/// Largest extent drawn, metres: a dance covers a stage (AIST++'s fit in 10 m); a motion
/// spanning more is in the wrong units or corrupt, and would shrink the dancer to a dot.
const MAX_SPAN_M: f64 = 1000.0;

/// Grid lines after the first from `lo` to `hi` (both on the grid); bounded because the span is.
fn grid_lines(lo: f32, hi: f32) -> usize {
    ((f64::from(hi) - f64::from(lo)) / f64::from(GRID_STEP_M))
        .round()
        .clamp(0.0, MAX_SPAN_M / f64::from(GRID_STEP_M) + 2.0) as usize
}

/// GIF frame delays (1/100 s) for frames `0, step, 2·step, …` of `frames` at `fps`: each frame
/// lasts until the next one starts, and the delays are differences of rounded cumulative times,
/// so the rounding never accumulates: the GIF lasts `frames / fps` to the nearest 1/100 s (a
/// 61.5 s dance at 60 fps drawn every 4th frame alternates 7 and 6, not 7 every time = 64.6 s).
fn gif_delays(frames: usize, step: usize, fps: f32) -> Vec<u16> {
    let centis = |frame: usize| (frame as f64 * 100.0 / f64::from(fps)).round();
    (0..frames)
        .step_by(step)
        .map(|f| {
            let d = centis((f + step).min(frames)) - centis(f);
            // Viewers show delays under 2 (20 ms) as 100 ms; the cap is the field's range.
            d.clamp(2.0, f64::from(u16::MAX)) as u16
        })
        .collect()
}

fn check_size(path: &Path, w: u32, h: u32) -> Result<()> {
    if !(16..=4096).contains(&w) || !(16..=4096).contains(&h) {
        return Err(Error::invalid(
            path,
            format!("image size {w}×{h} out of range (16..=4096)"),
        ));
    }
    Ok(())
}

/// Draw the motion as an animated, looping GIF (frames skipped down to `max_fps`).
pub fn render_gif(m: &MotionFile, path: &Path, opts: &RenderOptions) -> Result<()> {
    check_size(path, opts.width, opts.height)?;
    let scene = Scene::new(m, path, opts)?;
    let (w, h) = (opts.width as usize, opts.height as usize);
    let cam = scene.camera(w, h, opts);
    let t = m.joints.shape()[0];
    let step = (m.fps / opts.max_fps.max(1.0)).ceil().max(1.0) as usize;
    let delays = gif_delays(t, step, m.fps);
    let palette: Vec<u8> = PALETTE.iter().flatten().copied().collect();
    let enc_err = |e: gif::EncodingError| Error::Encode {
        path: path.to_path_buf(),
        reason: e.to_string(),
    };
    let mut out = Vec::new();
    {
        let mut enc = gif::Encoder::new(&mut out, w as u16, h as u16, &palette).map_err(enc_err)?;
        enc.set_repeat(gif::Repeat::Infinite).map_err(enc_err)?;
        for (f, delay) in (0..t).step_by(step).zip(delays) {
            let mut c = Canvas::new(w, h);
            scene.draw(&mut c, &cam, f);
            c.text(6, h - 16, &format!("{:.2}s", f as f32 / m.fps), 2, TEXT);
            let frame = gif::Frame {
                width: w as u16,
                height: h as u16,
                delay,
                buffer: std::borrow::Cow::Owned(c.px),
                ..Default::default()
            };
            enc.write_frame(&frame).map_err(enc_err)?;
        }
    }
    write_atomic_bytes(path, &out)
}

/// Draw `sheet_columns × sheet_rows` evenly spaced frames as one RGB PNG, each tile labelled
/// with its time.
pub fn render_contact_sheet(m: &MotionFile, path: &Path, opts: &RenderOptions) -> Result<()> {
    check_size(path, opts.width, opts.height)?;
    let (cols, rows) = (
        opts.sheet_columns.clamp(1, 16),
        opts.sheet_rows.clamp(1, 16),
    );
    let scene = Scene::new(m, path, opts)?;
    let (tw, th) = (opts.width as usize, opts.height as usize);
    let cam = scene.camera(tw, th, opts);
    let t = m.joints.shape()[0];
    let n = cols * rows;
    let mut sheet = Canvas::new(tw * cols, th * rows);
    for i in 0..n {
        // Evenly spaced, first and last frame included.
        let f = if n == 1 { 0 } else { i * (t - 1) / (n - 1) };
        let mut c = Canvas::new(tw, th);
        scene.draw(&mut c, &cam, f);
        c.text(6, th - 16, &format!("{:.2}s", f as f32 / m.fps), 2, TEXT);
        c.rect(0, 0, tw, th, BORDER);
        let (ox, oy) = ((i % cols) * tw, (i / cols) * th);
        for y in 0..th {
            let dst = (oy + y) * sheet.w + ox;
            sheet.px[dst..dst + tw].copy_from_slice(&c.px[y * tw..(y + 1) * tw]);
        }
    }
    let mut rgb = Vec::with_capacity(sheet.px.len() * 3);
    for p in &sheet.px {
        rgb.extend_from_slice(&PALETTE[usize::from(*p)]);
    }
    let enc_err = |e: png::EncodingError| Error::Encode {
        path: path.to_path_buf(),
        reason: e.to_string(),
    };
    let mut out = Vec::new();
    {
        let mut enc = png::Encoder::new(&mut out, sheet.w as u32, sheet.h as u32);
        enc.set_color(png::ColorType::Rgb);
        enc.set_depth(png::BitDepth::Eight);
        let mut wr = enc.write_header().map_err(enc_err)?;
        wr.write_image_data(&rgb).map_err(enc_err)?;
        wr.finish().map_err(enc_err)?;
    }
    write_atomic_bytes(path, &out)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::AistppMotion;
    use crate::skeleton::SkeletonKind;

    fn motion() -> MotionFile {
        let p = Path::new(env!("CARGO_MANIFEST_DIR"))
            .join("../../shared/fixtures/motion/aistpp_gBR_sBM_cAll_d04_mBR0_ch01.pkl");
        let m = AistppMotion::read(&p).unwrap();
        let j = crate::resample_joints(&m.joints(), 60.0, 30.0).unwrap();
        MotionFile::from_joints(30.0, SkeletonKind::Smpl24, j)
    }

    #[test]
    fn gif_and_sheet_are_valid_images_with_skeleton_pixels() {
        let dir = tempfile::tempdir().unwrap();
        let m = motion();
        let gif_path = dir.path().join("a.gif");
        render_gif(&m, &gif_path, &RenderOptions::default()).unwrap();
        let mut dec = gif::DecodeOptions::new();
        dec.set_color_output(gif::ColorOutput::Indexed);
        let mut r = dec
            .read_info(std::fs::File::open(&gif_path).unwrap())
            .unwrap();
        let mut frames = 0;
        while let Some(f) = r.read_next_frame().unwrap() {
            // Every frame shows left and right limbs and the dark joints.
            for colour in [LEFT, RIGHT, JOINT] {
                assert!(
                    f.buffer.iter().filter(|p| **p == colour).count() > 20,
                    "frame {frames} lacks colour {colour}"
                );
            }
            frames += 1;
        }
        // 360 frames at 30 fps drawn at 15 fps.
        assert_eq!(frames, 180);

        let png_path = dir.path().join("a.png");
        render_contact_sheet(&m, &png_path, &RenderOptions::default()).unwrap();
        let dec = png::Decoder::new(std::io::BufReader::new(
            std::fs::File::open(&png_path).unwrap(),
        ));
        let r = dec.read_info().unwrap();
        assert_eq!((r.info().width, r.info().height), (360 * 4, 360 * 3));
    }

    #[test]
    fn feet_in_contact_are_marked() {
        let m = motion();
        let s = Scene::new(&m, Path::new("x.gif"), &RenderOptions::default()).unwrap();
        let frames_with_contact = s.contact.iter().filter(|c| c.iter().any(|x| *x)).count();
        // A dancer has at least one foot planted most of the time.
        assert!(
            frames_with_contact > m.joints.shape()[0] / 2,
            "{frames_with_contact}"
        );
    }

    #[test]
    fn gif_lasts_as_long_as_the_motion() {
        // 61.5 s at 60 fps drawn every 4th frame: 923 GIF frames of 6.67 cs. Rounded one by one
        // (7 cs) the GIF lasted 64.61 s; the delays must add up to 6150 cs.
        let delays = gif_delays(3690, 4, 60.0);
        assert_eq!(delays.len(), 923);
        assert_eq!(delays.iter().map(|d| u32::from(*d)).sum::<u32>(), 6150);
        // The last frame only lasts until the motion ends (3690 = 922·4 + 2 frames: 2/60 s).
        let (last, rest) = delays.split_last().unwrap();
        assert!(rest.iter().all(|d| (6..=7).contains(d)), "{rest:?}");
        assert_eq!(*last, 3);
        // And the encoded file says so.
        let base = motion();
        let joints = Array3::from_shape_fn((3690, 24, 3), |(t, j, c)| {
            base.joints[[t % base.joints.shape()[0], j, c]]
        });
        let m = MotionFile::from_joints(60.0, SkeletonKind::Smpl24, joints);
        let dir = tempfile::tempdir().unwrap();
        let p = dir.path().join("long.gif");
        let mut opts = RenderOptions::default();
        (opts.width, opts.height) = (16, 16);
        render_gif(&m, &p, &opts).unwrap();
        let mut r = gif::DecodeOptions::new()
            .read_info(std::fs::File::open(&p).unwrap())
            .unwrap();
        let mut total = 0u32;
        while let Some(f) = r.read_next_frame().unwrap() {
            total += u32::from(f.delay);
        }
        assert_eq!(total, 6150);
    }

    #[test]
    fn far_away_or_absurdly_large_motion_terminates() {
        let dir = tempfile::tempdir().unwrap();
        let p = dir.path().join("x.png");
        let mut opts = RenderOptions::default();
        (opts.width, opts.height) = (32, 32);
        // A dance 30 km from the origin: f32 `x += 0.5` stops advancing there (ulp 2 m).
        let mut m = motion();
        m.joints
            .slice_mut(ndarray::s![.., .., 0])
            .mapv_inplace(|x| x + 3.0e7);
        render_contact_sheet(&m, &p, &opts).unwrap();
        // Coordinates of 1e30 m: refused with the reason (the motion value bound), not drawn
        // for ever.
        let mut m = motion();
        m.joints[[5, 3, 2]] = 1.0e30;
        let e = render_contact_sheet(&m, &p, &opts).unwrap_err().to_string();
        assert!(e.contains("1e30") && e.contains("x.png"), "{e}");
    }

    #[test]
    fn empty_or_nan_motion_is_an_error() {
        let dir = tempfile::tempdir().unwrap();
        let p = dir.path().join("x.gif");
        let m = MotionFile::from_joints(30.0, SkeletonKind::Smpl24, Array3::zeros((0, 24, 3)));
        assert!(
            render_gif(&m, &p, &RenderOptions::default())
                .unwrap_err()
                .to_string()
                .contains("no frames")
        );
        let mut j = Array3::zeros((3, 24, 3));
        j[[1, 2, 1]] = f32::NAN;
        let m = MotionFile::from_joints(30.0, SkeletonKind::Smpl24, j);
        assert!(
            render_contact_sheet(&m, &p, &RenderOptions::default())
                .unwrap_err()
                .to_string()
                .contains("NaN")
        );
        assert!(!p.exists());
    }
}
