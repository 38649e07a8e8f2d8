#![no_main]

#[allow(dead_code)]
#[path = "../../tests/common/readers.rs"]
mod readers;

libfuzzer_sys::fuzz_target!(
    init: {
        // The reader contains a panic inside mshio (stickslip::io::contain_panic) and
        // reports the file as unreadable; libFuzzer's hook would abort on it. Such panics
        // are printed (to be counted) and left to unwind; every other panic aborts.
        // STICKSLIP_FUZZ_STRICT=1 makes a contained panic abort too, so libFuzzer saves
        // its input as a crash.
        let strict = std::env::var_os("STICKSLIP_FUZZ_STRICT").is_some();
        let abort = std::panic::take_hook();
        std::panic::set_hook(Box::new(move |info| {
            if stickslip::io::panic_is_contained() && !strict {
                eprintln!("contained panic: {info}");
            } else {
                abort(info);
            }
        }));
    },
    |data: &[u8]| readers::gmsh(data)
);
