//! Checksums of the navigation formats.

/// NovAtel's CRC-32 (OEM firmware reference manual, "32-bit CRC"): the reflected polynomial
/// 0xEDB88320 with an initial value of 0 and no final inversion, over the header and message.
pub fn novatel_crc32(bytes: &[u8]) -> u32 {
    let mut crc = 0u32;
    for &b in bytes {
        crc = (crc >> 8) ^ NOVATEL_TABLE[((crc ^ b as u32) & 0xff) as usize];
    }
    crc
}

const NOVATEL_TABLE: [u32; 256] = {
    let mut table = [0u32; 256];
    let mut i = 0;
    while i < 256 {
        let mut c = i as u32;
        let mut k = 0;
        while k < 8 {
            c = if c & 1 != 0 {
                (c >> 1) ^ 0xEDB8_8320
            } else {
                c >> 1
            };
            k += 1;
        }
        table[i] = c;
        i += 1;
    }
    table
};

/// NMEA 0183 checksum: XOR of every byte between `$` (or `!`) and `*`, exclusive.
pub fn nmea_xor(body: &[u8]) -> u8 {
    body.iter().fold(0u8, |a, b| a ^ b)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn nmea_checksum_of_a_known_sentence() {
        // From the OxTS log in the fixtures: `$GPGGA,...*15`.
        let s = b"GPGGA,204132.10,4205.733715,N,08802.040978,W,2,08,1.0,221.921,M,,,3,0138";
        assert_eq!(nmea_xor(s), 0x15);
    }

    #[test]
    fn novatel_crc_is_the_bitwise_definition() {
        // The table-driven form equals the bit-at-a-time definition on arbitrary bytes.
        let data: Vec<u8> = (0..300u32).map(|i| (i * 37 + 11) as u8).collect();
        let mut crc = 0u32;
        for &b in &data {
            let mut c = (crc ^ b as u32) & 0xff;
            for _ in 0..8 {
                c = if c & 1 != 0 {
                    (c >> 1) ^ 0xEDB8_8320
                } else {
                    c >> 1
                };
            }
            crc = (crc >> 8) ^ c;
        }
        assert_eq!(novatel_crc32(&data), crc);
        assert_eq!(novatel_crc32(&[]), 0);
    }
}
