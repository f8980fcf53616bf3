//! Fuzz the ROS 2 message decoders of recordings (`headalign_io::recordings::cdr` and the
//! image conversion of `headalign_io::recordings::rosbag`): any bytes give a message (an
//! image converts to grey or is refused) or a typed error, never a panic or a huge
//! allocation.
#![no_main]

use headalign_io::recordings::{cdr, rosbag};
use libfuzzer_sys::fuzz_target;

fuzz_target!(|data: &[u8]| {
    if let Ok(img) = cdr::image(data) {
        if let Ok(grey) = rosbag::gray_from_image(&img) {
            assert_eq!(grey.size(), [img.width, img.height]);
        }
    }
    let _ = cdr::compressed_image(data);
    if let Ok(js) = cdr::joint_state(data) {
        assert_eq!(js.name.len(), js.position.len());
    }
});
