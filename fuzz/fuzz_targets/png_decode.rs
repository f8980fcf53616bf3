//! Fuzz image decoding (`headalign_vision::GrayImage::decode`, what `GrayImage::load`
//! and the image-session reader use) and the session reader's texture check: any bytes
//! give an image within the size limits or an error, never a panic or an allocation
//! beyond the limit. The limits here are tighter than the defaults (one million pixels,
//! 64 MiB) so the fuzzer spends its time in the parsers rather than filling huge declared
//! images (decoding time grows with the declared size: a 673-byte JPEG declaring 50
//! million pixels took 10 s; the default `MAX_PIXELS` now refuses it from the header).
#![no_main]

use headalign_vision::GrayImage;
use headalign_vision::image::DecodeLimits;
use libfuzzer_sys::fuzz_target;

fuzz_target!(|data: &[u8]| {
    let limits = DecodeLimits { max_side: 4096, max_pixels: 1 << 20, max_bytes: 64 << 20 };
    if let Ok(img) = GrayImage::decode_with_limits(data, &limits) {
        assert!(img.width() <= limits.max_side && img.height() <= limits.max_side);
        assert!(u64::from(img.width()) * u64::from(img.height()) <= limits.max_pixels);
        assert_eq!(img.pixels().len(), img.width() as usize * img.height() as usize);
        let _ = headalign_io::session::check_image(&img, "left.png");
    }
});
