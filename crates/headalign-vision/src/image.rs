//! The grey image type shared by the renderer, the vision front end and the platform
//! traits: 8-bit, row-major, `width x height` (both at least 1), with PNG/JPEG I/O.
//!
//! Pitfalls: colour files are converted to luma on load (ITU-R BT.601 weights, as the
//! `image` crate does); 16-bit files are scaled to 8 bits.

use std::path::Path;

use crate::VisionError;

/// An 8-bit grey image, row-major.
#[derive(Clone, PartialEq, Eq)]
pub struct GrayImage {
    width: u32,
    height: u32,
    data: Vec<u8>,
}

impl std::fmt::Debug for GrayImage {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        write!(f, "GrayImage({}x{})", self.width, self.height)
    }
}

impl GrayImage {
    /// An image from its row-major pixels; errors if a side is zero or the buffer length
    /// is not `width * height`.
    pub fn new(width: u32, height: u32, data: Vec<u8>) -> Result<Self, VisionError> {
        if width == 0 || height == 0 {
            return Err(VisionError::InvalidImage(format!("zero size {width}x{height}")));
        }
        let n = width as usize * height as usize;
        if data.len() != n {
            return Err(VisionError::InvalidImage(format!(
                "{width}x{height} needs {n} pixels, got {}",
                data.len()
            )));
        }
        Ok(Self { width, height, data })
    }

    /// A constant image (zero sides are raised to 1).
    pub fn filled(width: u32, height: u32, value: u8) -> Self {
        let (width, height) = (width.max(1), height.max(1));
        Self { width, height, data: vec![value; width as usize * height as usize] }
    }

    /// Width in pixels.
    pub fn width(&self) -> u32 {
        self.width
    }

    /// Height in pixels.
    pub fn height(&self) -> u32 {
        self.height
    }

    /// `[width, height]`.
    pub fn size(&self) -> [u32; 2] {
        [self.width, self.height]
    }

    /// The row-major pixels.
    pub fn pixels(&self) -> &[u8] {
        &self.data
    }

    /// The row-major pixels, mutable.
    pub fn pixels_mut(&mut self) -> &mut [u8] {
        &mut self.data
    }

    /// Row `y` (panics if `y >= height`, a programming error, never data).
    pub fn row(&self, y: u32) -> &[u8] {
        let w = self.width as usize;
        &self.data[y as usize * w..(y as usize + 1) * w]
    }

    /// Pixel `(x, y)`, `None` outside the image.
    pub fn get(&self, x: u32, y: u32) -> Option<u8> {
        (x < self.width && y < self.height).then(|| self.data[y as usize * self.width as usize + x as usize])
    }

    /// Read a PNG or JPEG file (colour is converted to grey).
    pub fn load(path: &Path) -> Result<Self, VisionError> {
        let read = |why: String| VisionError::Read { path: path.to_path_buf(), why };
        let img = image::ImageReader::open(path)
            .map_err(|e| read(e.to_string()))?
            .with_guessed_format()
            .map_err(|e| read(e.to_string()))?
            .decode()
            .map_err(|e| read(e.to_string()))?
            .into_luma8();
        let (w, h) = img.dimensions();
        Self::new(w, h, img.into_raw()).map_err(|e| read(e.to_string()))
    }

    /// Write a PNG (or JPEG, by the file extension).
    pub fn save(&self, path: &Path) -> Result<(), VisionError> {
        let buf =
            image::GrayImage::from_raw(self.width, self.height, self.data.clone()).ok_or_else(|| {
                VisionError::Write { path: path.to_path_buf(), why: "buffer does not match size".into() }
            })?;
        buf.save(path).map_err(|e| VisionError::Write { path: path.to_path_buf(), why: e.to_string() })
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn png_round_trip_and_errors() {
        let img = GrayImage::new(3, 2, vec![0, 10, 20, 30, 40, 255]).unwrap();
        let dir = std::env::temp_dir().join(format!("headalign-vision-{}", std::process::id()));
        std::fs::create_dir_all(&dir).unwrap();
        let p = dir.join("a.png");
        img.save(&p).unwrap();
        assert_eq!(GrayImage::load(&p).unwrap(), img);
        assert_eq!(img.get(2, 1), Some(255));
        assert_eq!(img.get(3, 0), None);
        assert!(GrayImage::new(0, 2, vec![]).is_err());
        assert!(GrayImage::new(2, 2, vec![0; 3]).is_err());
        let missing = dir.join("missing.png");
        let e = GrayImage::load(&missing).unwrap_err().to_string();
        assert!(e.contains("missing.png"), "{e}");
        std::fs::write(dir.join("bad.png"), b"not a png").unwrap();
        assert!(GrayImage::load(&dir.join("bad.png")).is_err());
        std::fs::remove_dir_all(&dir).ok();
    }
}
