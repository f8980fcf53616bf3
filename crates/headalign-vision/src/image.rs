//! The grey image type shared by the renderer, the vision front end and the platform
//! traits: 8-bit, row-major, `width x height` (both at least 1), with PNG/JPEG I/O.
//!
//! Pitfalls: colour files are converted to luma on load (ITU-R BT.601 weights, as the
//! `image` crate does); 16-bit files are scaled to 8 bits. Files are untrusted input: a
//! header claiming a huge image is refused before anything is allocated (at most
//! [`MAX_SIDE`] pixels a side, [`MAX_PIXELS`] pixels and [`MAX_DECODE_BYTES`] of decoder
//! memory; [`DecodeLimits`]), so a corrupt or hostile PNG is an error, never an
//! out-of-memory abort. Decoding time grows with the declared size, not the file size: a
//! 673-byte progressive JPEG declaring 4099 x 12336 pixels took 10 s to decode (found by
//! fuzzing: `fuzz/`, target `png_decode`); the pixel limit bounds that.

use std::path::Path;

use crate::VisionError;

/// Largest width or height a file may declare, pixels (16384: four times a 4K frame).
pub const MAX_SIDE: u32 = 16_384;

/// Largest number of pixels a file may declare (36 million: an 8K UHD frame, 7680 x 4320,
/// fits; the simulated cameras have 0.44 million).
pub const MAX_PIXELS: u64 = 36_000_000;

/// Most memory the decoder may allocate for one file, bytes (512 MiB, the `image`
/// crate's own default).
pub const MAX_DECODE_BYTES: u64 = 512 * 1024 * 1024;

/// Limits on what a decoded file may declare; defaults [`MAX_SIDE`], [`MAX_PIXELS`],
/// [`MAX_DECODE_BYTES`].
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct DecodeLimits {
    /// Largest width or height, pixels.
    pub max_side: u32,
    /// Largest `width * height`.
    pub max_pixels: u64,
    /// Most memory the decoder may allocate, bytes.
    pub max_bytes: u64,
}

impl Default for DecodeLimits {
    fn default() -> Self {
        Self { max_side: MAX_SIDE, max_pixels: MAX_PIXELS, max_bytes: MAX_DECODE_BYTES }
    }
}

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

    /// Read a PNG or JPEG file (colour is converted to grey). Errors name the file.
    pub fn load(path: &Path) -> Result<Self, VisionError> {
        let read = |why: String| VisionError::Read { path: path.to_path_buf(), why };
        if path.is_dir() {
            return Err(read("is a directory, not an image file".into()));
        }
        let bytes = std::fs::read(path).map_err(|e| read(e.to_string()))?;
        Self::decode(&bytes).map_err(|e| match e {
            VisionError::InvalidImage(why) => read(why),
            other => other,
        })
    }

    /// Decode a PNG or JPEG held in memory (the format is guessed from the bytes; colour
    /// is converted to grey) within the default [`DecodeLimits`]. Bad, truncated or
    /// oversized data is [`VisionError::InvalidImage`], never a panic or a huge allocation.
    pub fn decode(bytes: &[u8]) -> Result<Self, VisionError> {
        Self::decode_with_limits(bytes, &DecodeLimits::default())
    }

    /// [`GrayImage::decode`] within the given limits (the header is read first; a
    /// declared size beyond them is an error before any pixel is decoded).
    pub fn decode_with_limits(bytes: &[u8], limits: &DecodeLimits) -> Result<Self, VisionError> {
        let bad = |why: String| VisionError::InvalidImage(why);
        let reader = || -> Result<_, VisionError> {
            let mut reader = image::ImageReader::new(std::io::Cursor::new(bytes))
                .with_guessed_format()
                .map_err(|e| bad(e.to_string()))?;
            let mut l = image::Limits::default();
            l.max_image_width = Some(limits.max_side);
            l.max_image_height = Some(limits.max_side);
            l.max_alloc = Some(limits.max_bytes);
            reader.limits(l);
            Ok(reader)
        };
        let (w, h) = reader()?.into_dimensions().map_err(|e| bad(e.to_string()))?;
        if u64::from(w) * u64::from(h) > limits.max_pixels {
            return Err(bad(format!(
                "the file declares {w}x{h} pixels, more than the limit of {} million",
                limits.max_pixels as f64 / 1e6
            )));
        }
        let img = reader()?.decode().map_err(|e| bad(e.to_string()))?.into_luma8();
        let (w, h) = img.dimensions();
        Self::new(w, h, img.into_raw()).map_err(|e| bad(e.to_string()))
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
        let dir = crate::test_util::scratch_dir("png-round-trip");
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
        assert!(GrayImage::load(&dir).unwrap_err().to_string().contains("directory"));
        std::fs::remove_dir_all(&dir).ok();
    }

    /// A valid PNG header declaring a 1,000,000 x 1,000,000 image (no pixel data): refused
    /// by the limits before any allocation. And no prefix of a valid PNG panics.
    #[test]
    fn decode_refuses_huge_and_truncated_data() {
        let mut png = b"\x89PNG\r\n\x1a\n\0\0\0\rIHDR".to_vec();
        png.extend_from_slice(&1_000_000u32.to_be_bytes());
        png.extend_from_slice(&1_000_000u32.to_be_bytes());
        png.extend_from_slice(&[8, 0, 0, 0, 0]);
        let crc = crc32(&png[12..]);
        png.extend_from_slice(&crc.to_be_bytes());
        let e = GrayImage::decode(&png).unwrap_err().to_string();
        assert!(e.contains("invalid image"), "{e}");
        // Within the side limit but beyond the pixel limit: refused from the header.
        let small = DecodeLimits { max_pixels: 19, ..DecodeLimits::default() };
        let img = GrayImage::new(5, 4, (0..20).map(|i| (i * 13) as u8).collect()).unwrap();
        let dir = crate::test_util::scratch_dir("png-truncated");
        let p = dir.join("a.png");
        img.save(&p).unwrap();
        let bytes = std::fs::read(&p).unwrap();
        assert_eq!(GrayImage::decode(&bytes).unwrap(), img);
        let e = GrayImage::decode_with_limits(&bytes, &small).unwrap_err().to_string();
        assert!(e.contains("declares 5x4 pixels"), "{e}");
        let tight = DecodeLimits { max_pixels: 20, max_side: 5, ..DecodeLimits::default() };
        assert_eq!(GrayImage::decode_with_limits(&bytes, &tight).unwrap(), img);
        // A prefix is an error, or (cut only after the image data, e.g. in IEND) the image.
        for n in 0..bytes.len() {
            if let Ok(got) = GrayImage::decode(&bytes[..n]) {
                assert_eq!(got, img, "prefix {n} of {} decoded to another image", bytes.len());
            }
        }
        assert!(GrayImage::decode(&bytes[..bytes.len() / 2]).is_err());
        std::fs::remove_dir_all(&dir).ok();
    }

    /// CRC-32 (IEEE), to build PNG chunks by hand.
    fn crc32(data: &[u8]) -> u32 {
        let mut c = 0xffff_ffffu32;
        for &b in data {
            c ^= u32::from(b);
            for _ in 0..8 {
                c = if c & 1 != 0 { 0xedb8_8320 ^ (c >> 1) } else { c >> 1 };
            }
        }
        !c
    }
}
