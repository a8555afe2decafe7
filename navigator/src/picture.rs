//! Per-frame match pictures like a TRN flight report's: the camera image in
//! grey; for each correlation match, where the pose guess predicted the
//! landmark (blue dot) with a line to where it was found (a ring, green for
//! an inlier of the solution, red for an outlier). Pure drawing; the caller
//! writes the PNG.

use image::{Rgb, RgbImage};
use trn_camera::Pixel;
use trn_flight::MatchRecord;

use crate::image::GreyImage;

pub const INLIER: Rgb<u8> = Rgb([40, 220, 60]);
pub const OUTLIER: Rgb<u8> = Rgb([235, 40, 40]);
pub const PREDICTED: Rgb<u8> = Rgb([60, 120, 255]);

/// The picture of one frame; `guess_px[i]` is where the pose guess put
/// `matches[i]`'s landmark (`None`: behind the camera).
pub fn draw_matches(img: &GreyImage, matches: &[MatchRecord], guess_px: &[Option<Pixel>]) -> RgbImage {
    let mut out = RgbImage::from_fn(img.width as u32, img.height as u32, |x, y| {
        // Dimmed so the marks stand out.
        let g = (img.data[y as usize * img.width + x as usize] * 0.7).clamp(0.0, 255.0) as u8;
        Rgb([g, g, g])
    });
    for (m, g) in matches.iter().zip(guess_px) {
        let found = Pixel::new(m.u, m.v);
        let colour = if m.inlier { INLIER } else { OUTLIER };
        if let Some(g) = g {
            line(&mut out, *g, found, PREDICTED);
            disc(&mut out, *g, 1.5, PREDICTED);
        }
        ring(&mut out, found, 4.0, colour);
    }
    out
}

fn put(img: &mut RgbImage, x: i64, y: i64, c: Rgb<u8>) {
    if x >= 0 && y >= 0 && (x as u32) < img.width() && (y as u32) < img.height() {
        img.put_pixel(x as u32, y as u32, c);
    }
}

/// A line between pixel centres (DDA), clipped to a sane length.
fn line(img: &mut RgbImage, a: Pixel, b: Pixel, c: Rgb<u8>) {
    let (du, dv) = (b.u - a.u, b.v - a.v);
    let n = du.abs().max(dv.abs()).ceil().min(4096.0) as usize;
    for k in 0..=n {
        let s = if n == 0 { 0.0 } else { k as f64 / n as f64 };
        put(img, (a.u + s * du).round() as i64, (a.v + s * dv).round() as i64, c);
    }
}

fn disc(img: &mut RgbImage, p: Pixel, r: f64, c: Rgb<u8>) {
    let ri = r.ceil() as i64;
    let (x0, y0) = (p.u.round() as i64, p.v.round() as i64);
    for y in -ri..=ri {
        for x in -ri..=ri {
            if ((x * x + y * y) as f64) <= r * r {
                put(img, x0 + x, y0 + y, c);
            }
        }
    }
}

fn ring(img: &mut RgbImage, p: Pixel, r: f64, c: Rgb<u8>) {
    let ri = (r + 1.0).ceil() as i64;
    let (x0, y0) = (p.u.round() as i64, p.v.round() as i64);
    for y in -ri..=ri {
        for x in -ri..=ri {
            let d = ((x * x + y * y) as f64).sqrt();
            if (d - r).abs() <= 0.6 {
                put(img, x0 + x, y0 + y, c);
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn record(u: f64, v: f64, inlier: bool) -> MatchRecord {
        MatchRecord {
            t: 0.0,
            landmark: 1,
            u,
            v,
            pred_u: u,
            pred_v: v,
            residual_px: 0.0,
            inlier,
            landmark_ecef: None,
            sigma_px: None,
        }
    }

    #[test]
    fn marks_land_where_the_matches_are() {
        let img = GreyImage { width: 64, height: 48, data: vec![100.0; 64 * 48] };
        let matches = [record(20.0, 20.0, true), record(50.0, 30.0, false)];
        let guess = [Some(Pixel::new(10.0, 20.0)), None];
        let pic = draw_matches(&img, &matches, &guess);
        assert_eq!(pic.dimensions(), (64, 48));
        // Background dimmed grey, untouched far from the marks.
        assert_eq!(*pic.get_pixel(60, 5), Rgb([70, 70, 70]));
        // Rings 4 px around each match, in the inlier / outlier colour.
        assert_eq!(*pic.get_pixel(24, 20), INLIER);
        assert_eq!(*pic.get_pixel(50, 26), OUTLIER);
        // The ring's centre stays clear; the guess and the line to it are blue.
        assert_eq!(*pic.get_pixel(50, 30), Rgb([70, 70, 70]));
        assert_eq!(*pic.get_pixel(10, 20), PREDICTED);
        assert_eq!(*pic.get_pixel(14, 20), PREDICTED);
        // No line for the match without a guess.
        assert_eq!(*pic.get_pixel(40, 30), Rgb([70, 70, 70]));
    }

    #[test]
    fn marks_off_the_image_are_clipped() {
        let img = GreyImage { width: 8, height: 8, data: vec![0.0; 64] };
        let matches = [record(-100.0, 3.0, true)];
        let pic = draw_matches(&img, &matches, &[Some(Pixel::new(1e9, -1e9))]);
        assert_eq!(pic.dimensions(), (8, 8));
    }
}
