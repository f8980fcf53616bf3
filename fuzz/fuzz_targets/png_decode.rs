//! Fuzz image decoding (`headalign_vision::GrayImage::decode`, what `GrayImage::load`
//! and the image-session reader use) and the session reader's texture check: any bytes
//! give an image within the size limits or an error, never a panic or an allocation
//! beyond `MAX_DECODE_BYTES`.
#![no_main]

use headalign_vision::GrayImage;
use headalign_vision::image::MAX_SIDE;
use libfuzzer_sys::fuzz_target;

fuzz_target!(|data: &[u8]| {
    if let Ok(img) = GrayImage::decode(data) {
        assert!(img.width() <= MAX_SIDE && img.height() <= MAX_SIDE);
        assert_eq!(img.pixels().len(), img.width() as usize * img.height() as usize);
        let _ = headalign::session::check_image(&img, "left.png");
    }
});
